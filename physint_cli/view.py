"""``physint view``: a dataset, a run or a recording in the rerun viewer, or saved as .rrd."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BadInput


def _start(save: Path | None, name: str):
    import rerun as rr

    rr.init(f"physint-{name}", spawn=False)
    if save is not None:
        save.parent.mkdir(parents=True, exist_ok=True)
        rr.save(str(save))
    else:
        try:
            rr.spawn(connect=True)
        except Exception as exc:
            raise BadInput(f"cannot open the rerun viewer here ({str(exc).splitlines()[0]}); use --save FILE.rrd") from None
    return rr


def _log_array(rr, path: str, value: np.ndarray) -> None:
    value = np.asarray(value)
    if value.dtype == np.uint8 and value.ndim == 3 and value.shape[-1] in (1, 3, 4):
        rr.log(path, rr.Image(value))
    elif value.dtype == np.uint8 and value.ndim == 2:
        rr.log(path, rr.Image(value))
    elif np.issubdtype(value.dtype, np.integer) and value.ndim == 2:
        rr.log(path, rr.SegmentationImage(value.astype(np.int32) + 2))  # -2/-1 conventions -> non-negative ids
    elif value.ndim == 0 or value.size == 1:
        rr.log(path, rr.Scalars([float(value.reshape(-1)[0])]))
    elif value.ndim == 1 and value.size <= 16 and np.issubdtype(value.dtype, np.number):
        rr.log(path, rr.Scalars(value.astype(float)))
    elif value.ndim == 2 and value.shape[-1] == 3 and np.issubdtype(value.dtype, np.floating):
        rr.log(path, rr.Points3D(value))


def view_dataset(rr, root: Path, limit: int) -> dict[str, Any]:
    from .datasets import ShardedDataset, read_manifest

    manifest = read_manifest(root)
    summary = {k: v for k, v in manifest.items() if k != "shards"}
    rr.log("manifest", rr.TextDocument(json.dumps(summary, indent=2, default=str)), static=True)
    shown = 0
    for split in manifest["splits"]:
        ds = ShardedDataset(root, split)
        for i in range(min(limit, len(ds))):
            rr.set_time("record", sequence=i)
            for key, value in ds[i].items():
                _log_array(rr, f"{split}/{key}", value)
            shown += 1
        ds.close()
    return {"kind": "dataset", "records_shown": shown}


def view_run(rr, root: Path) -> dict[str, Any]:
    info = json.loads((root / "run.json").read_text())
    rr.log("run", rr.TextDocument(json.dumps(info, indent=2, default=str)), static=True)
    points = 0
    curves = root / "metrics.jsonl"
    if curves.exists():
        for line in curves.read_text().splitlines():
            row = json.loads(line)
            rr.set_time("step", sequence=int(row.get("step", points)))
            for k, v in row.items():
                if k not in ("step", "time") and isinstance(v, (int, float)):
                    rr.log(f"metrics/{k}", rr.Scalars([float(v)]))
            points += 1
    if (root / "metrics.json").exists():
        rr.log("metrics.json", rr.TextDocument((root / "metrics.json").read_text()), static=True)
    images = 0
    for png in sorted((root / "artifacts").glob("*.png")):
        rr.log(f"artifacts/{png.stem}", rr.EncodedImage(path=png), static=True)
        images += 1
    for rrd in sorted((root / "artifacts").glob("*.rrd")):
        rr.log_file_from_path(rrd)
    return {"kind": "run", "curve_points": points, "images": images}


def view(path: Path, save: Path | None = None, limit: int = 32) -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise BadInput(f"{path}: no such file or directory")
    if path.suffix == ".rrd" and path.is_file():
        if save is not None:
            shutil.copyfile(path, save)
            return {"kind": "recording", "saved": str(save)}
        rr = _start(None, path.stem)
        rr.log_file_from_path(path)
        return {"kind": "recording", "opened": str(path)}
    if (path / "manifest.json").exists():
        rr = _start(save, path.name)
        result = view_dataset(rr, path, limit)
    elif (path / "run.json").exists():
        rr = _start(save, path.name)
        result = view_run(rr, path)
    else:
        raise BadInput(f"{path} is not a physint dataset (manifest.json), run (run.json) or .rrd recording")
    if save is not None:
        rr.disconnect()
        result["saved"] = str(save)
    return {"path": str(path), **result}
