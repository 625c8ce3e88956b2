"""One on-disk dataset format for every method.

A dataset is a directory::

    manifest.json            method, scene, backend, preset, seed, resolved config, schema,
                             split counts, shards with checksums, stats, versions, times, status
    shards/train-00000.h5    one HDF5 file per work unit, records along the first axis
    shards/train-00000.h5.json   the shard's sidecar: sha256, record count, per-shard stats

Workers write shards independently. Every file is written to a temporary name and renamed,
and a shard only counts as finished once its sidecar exists, so an interrupted generation
resumes without losing or redoing a finished shard, and nothing half-written reads as
complete. The manifest's ``status`` is ``"complete"`` only after every shard is finished.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BadInput

MANIFEST = "manifest.json"
SHARDS = "shards"
FORMAT_VERSION = 1


# -- atomic writes ------------------------------------------------------------------------------

def atomic_write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(Path(path), (json.dumps(obj, indent=2, default=_json_default) + "\n").encode())


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_writable(directory: Path, what: str = "--out") -> Path:
    """Create ``directory`` (and parents) or raise BadInput saying it cannot be written."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise BadInput(f"{what} {directory}: cannot write there ({exc.strerror or exc}); choose another directory") from None
    return directory


# -- schema -------------------------------------------------------------------------------------

def add_up(stats: list[dict[str, Any]]) -> dict[str, Any]:
    """The work units' numeric statistics summed key by key (what a method's ``summarize`` starts from)."""
    total: dict[str, Any] = {}
    for s in stats:
        for k, v in s.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                total[k] = total.get(k, 0) + v
    return total


def schema_of(arrays: dict[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """``{field: {"dtype", "shape"}}`` with the per-record shape (without the leading axis)."""
    return {k: {"dtype": str(np.asarray(v).dtype), "shape": list(np.asarray(v).shape[1:])} for k, v in arrays.items()}


def _is_image(arr: np.ndarray) -> bool:
    return arr.dtype == np.uint8 and arr.ndim >= 3


# -- writing shards -----------------------------------------------------------------------------

def shard_path(root: Path, unit_name: str) -> Path:
    return Path(root) / SHARDS / f"{unit_name}.h5"


def shard_done(root: Path, unit_name: str) -> dict[str, Any] | None:
    """The sidecar of a finished shard, or None if the shard must be (re)made."""
    path = shard_path(root, unit_name)
    side = path.with_name(path.name + ".json")
    if not (path.exists() and side.exists()):
        return None
    try:
        return json.loads(side.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def write_shard(root: Path, unit_name: str, split: str, arrays: dict[str, np.ndarray],
                stats: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write one shard atomically, then its sidecar; returns the sidecar record."""
    import h5py

    counts = {len(np.asarray(v)) for v in arrays.values()}
    if len(counts) != 1:
        raise ValueError(f"shard {unit_name}: fields have different record counts {sorted(counts)}")
    n = counts.pop()
    path = shard_path(root, unit_name)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with h5py.File(tmp, "w") as f:
        f.attrs["split"] = split
        f.attrs["unit"] = unit_name
        f.attrs["count"] = n
        for key, value in arrays.items():
            arr = np.asarray(value)
            if _is_image(arr) and n > 0:
                # one record per chunk: random access reads only what it needs
                f.create_dataset(key, data=arr, chunks=(1, *arr.shape[1:]), compression="gzip", compression_opts=4, shuffle=True)
            else:
                f.create_dataset(key, data=arr)
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    record = {"file": f"{SHARDS}/{path.name}", "split": split, "count": int(n), "sha256": sha256_file(path),
              "bytes": path.stat().st_size, "schema": schema_of(arrays), "stats": stats or {}}
    atomic_write_json(path.with_name(path.name + ".json"), record)
    return record


# -- manifest -----------------------------------------------------------------------------------

def versions(*distributions: str) -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for d in ("physint", "numpy", "torch", "h5py", *distributions):
        try:
            out[d] = version(d)
        except PackageNotFoundError:
            pass
    return out


VECTOR_EXTENSIONS = (("avx2", "AVX2"), ("avx512f", "AVX-512"), ("avx512_bf16", "AVX512-BF16"), ("amx_tile", "AMX"))
ISA_CAPS = ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA")  # hold torch's and oneDNN's kernels to an older ISA


def machine(cpuinfo: str | None = None) -> dict[str, Any]:
    """The CPU a run or a dataset was made on, as its figures' provenance: model name, cores, the
    vector extensions that decide how fast it trains (``resolve_precision`` picks bf16 on AMX or
    AVX512-BF16), and any cap of torch's and oneDNN's kernels set in the environment (``held_to``:
    a newer CPU held to AVX2, say). ``cpuinfo``: the text of /proc/cpuinfo (read when None)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    name, flags = None, set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and name is None:
            name = value.strip()
        elif key.strip() == "flags" and not flags:
            flags = set(value.split())
    return {"cpu": name or platform.processor() or "unknown CPU", "cores": os.cpu_count(),
            "isa": [label for flag, label in VECTOR_EXTENSIONS if flag in flags],
            "held_to": {k: os.environ[k] for k in ISA_CAPS if os.environ.get(k)}}


def describe_machine(m: dict[str, Any]) -> str:
    """``machine()`` in one line: "Intel(R) Xeon(R) Processor, 2 cores, AVX2/AVX-512 (held to
    ATEN_CPU_CAPABILITY=avx2)"."""
    text = f"{m.get('cpu', 'unknown CPU')}, {m.get('cores', '?')} cores, {'/'.join(m.get('isa') or []) or 'no AVX2'}"
    held = m.get("held_to") or {}
    return text + (f" (held to {', '.join(f'{k}={v}' for k, v in held.items())})" if held else "")


def start_manifest(root: Path, header: dict[str, Any]) -> dict[str, Any]:
    """Write (or reuse, when resuming) the manifest of a dataset being generated."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / MANIFEST
    if path.exists():
        old = json.loads(path.read_text())
        same = {k: old.get(k) for k in ("method", "scene", "backend", "seed", "config")}
        new = {k: json.loads(json.dumps(header.get(k), default=_json_default)) for k in same}
        if same != new:
            diff = [k for k in same if same[k] != new[k]]
            raise BadInput(f"{root} already holds a different dataset (differs in {', '.join(diff)}); "
                           "choose another --out or delete it")
        if old.get("status") == "complete":
            return old
        header = {**old, **header, "created": old.get("created")}
    manifest = {"format": FORMAT_VERSION, "status": "incomplete", "created": _now(), **header}
    atomic_write_json(path, manifest)
    return manifest


def finish_manifest(root: Path, manifest: dict[str, Any], shards: list[dict[str, Any]],
                    stats: dict[str, Any], seconds: float) -> dict[str, Any]:
    splits: dict[str, int] = {}
    schema: dict[str, Any] = {}
    for s in shards:
        splits[s["split"]] = splits.get(s["split"], 0) + s["count"]
        schema = schema or s.get("schema", {})
    total = sum(splits.values())
    manifest = {**manifest, "status": "complete", "finished": _now(), "splits": splits, "records": total,
                "schema": schema, "stats": stats,
                "shards": [{k: s[k] for k in ("file", "split", "count", "sha256", "bytes")} for s in shards],
                "generation_seconds": round(seconds, 3)}
    atomic_write_json(Path(root) / MANIFEST, manifest)
    return manifest


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def read_manifest(root: Path, method: str | None = None) -> dict[str, Any]:
    """The manifest of a finished dataset, or BadInput saying what is wrong and what to do."""
    root = Path(root)
    path = root / MANIFEST
    if not root.is_dir():
        raise BadInput(f"no dataset at {root}: the directory does not exist; make one with `physint dataset {method or 'METHOD'}`")
    if not path.is_file():
        raise BadInput(f"no dataset at {root}: {MANIFEST} is missing; make one with `physint dataset {method or 'METHOD'}`")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        raise BadInput(f"dataset {root} is corrupted: {MANIFEST} is not valid JSON; regenerate it with `physint dataset`") from None
    if manifest.get("status") != "complete":
        raise BadInput(f"dataset {root} is incomplete (generation was interrupted); rerun the same `physint dataset` command to resume it")
    if method is not None and manifest.get("method") != method:
        raise BadInput(f"dataset {root} was made for method {manifest.get('method')!r}, not {method!r}")
    return manifest


def verify(root: Path) -> list[str]:
    """Problems found in a dataset's shards ("shards/x.h5: checksum mismatch"); empty if sound."""
    import h5py

    root = Path(root)
    manifest_path = root / MANIFEST
    if not manifest_path.is_file():
        raise BadInput(f"no dataset at {root}: {MANIFEST} is missing")
    try:
        manifest = json.loads(manifest_path.read_text())
    except json.JSONDecodeError:
        return [f"{MANIFEST}: not valid JSON"]
    problems = []
    if manifest.get("status") != "complete":
        problems.append(f"{MANIFEST}: generation incomplete (rerun `physint dataset` to resume)")
        records = []
        for side in sorted((root / SHARDS).glob("*.h5.json")):
            try:
                records.append(json.loads(side.read_text()))
            except json.JSONDecodeError:
                problems.append(f"{SHARDS}/{side.name}: sidecar is not valid JSON")
    else:
        records = manifest.get("shards", [])
    for rec in records:
        path = root / rec["file"]
        if not path.exists():
            problems.append(f"{rec['file']}: missing")
            continue
        if path.stat().st_size != rec.get("bytes", path.stat().st_size):
            problems.append(f"{rec['file']}: truncated ({path.stat().st_size} of {rec['bytes']} bytes)")
            continue
        if sha256_file(path) != rec["sha256"]:
            problems.append(f"{rec['file']}: checksum mismatch (corrupted)")
            continue
        try:
            with h5py.File(path, "r") as f:
                if int(f.attrs["count"]) != rec["count"]:
                    problems.append(f"{rec['file']}: holds {int(f.attrs['count'])} records, manifest says {rec['count']}")
        except OSError as exc:
            problems.append(f"{rec['file']}: unreadable HDF5 ({exc})")
    return problems


# -- reading ------------------------------------------------------------------------------------

IN_MEMORY_LIMIT = 2 << 30  # bytes: ``in_memory="auto"`` reads a split into memory up to this size


class ShardedDataset:
    """Random access to one split of a dataset, as a ``torch.utils.data.Dataset``.

    Records are read one at a time from the HDF5 shards; at most ``max_open`` shard files are
    kept open per process, so memory stays bounded whatever the dataset's size. Works with
    DataLoader worker processes (files are opened lazily in each process).

    ``in_memory=True`` reads the split's fields once, shard by shard, into arrays instead (each
    record decompressed once, not once per epoch: on a 2-core machine a shuffled pass over 25,200
    gzip-compressed 128 px images cost ~30 s in record reads); ``"auto"`` does so when they take at
    most ``IN_MEMORY_LIMIT`` bytes (:attr:`nbytes`) and streams otherwise.
    """

    def __init__(self, root: Path | str, split: str = "train", fields: list[str] | None = None,
                 transform=None, method: str | None = None, max_open: int = 8, in_memory: bool | str = False):
        self.root = Path(root)
        self.manifest = read_manifest(self.root, method)
        self.split = split
        self.shards = [s for s in self.manifest["shards"] if s["split"] == split]
        available = sorted({s["split"] for s in self.manifest["shards"]})
        if not self.shards:
            raise BadInput(f"dataset {self.root} has no {split!r} records; splits: {', '.join(available) or 'none'}")
        self.fields = fields or list(self.manifest["schema"])
        unknown_fields = [f for f in self.fields if f not in self.manifest["schema"]]
        if unknown_fields:
            raise BadInput(f"dataset {self.root} has no field(s) {', '.join(unknown_fields)}; fields: {', '.join(self.manifest['schema'])}")
        self.offsets = np.cumsum([0] + [s["count"] for s in self.shards])
        self.transform = transform
        self.max_open = max_open
        self._files: OrderedDict[str, Any] = OrderedDict()
        self._pid = os.getpid()
        if in_memory not in (True, False, "auto"):
            raise ValueError(f"in_memory must be True, False or 'auto', got {in_memory!r}")
        self.arrays: dict[str, np.ndarray] | None = None
        if in_memory is True or (in_memory == "auto" and self.nbytes <= IN_MEMORY_LIMIT):
            self.arrays = self._read_all()

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _read_all(self) -> dict[str, np.ndarray]:
        """Every record of the split, field by field, filled in shard by shard (one shard extra in memory)."""
        schema = self.manifest["schema"]
        arrays = {k: np.empty((len(self), *schema[k]["shape"]), dtype=schema[k]["dtype"]) for k in self.fields}
        for start, part in zip(self.offsets, self.shard_arrays()):
            for k, v in part.items():
                arrays[k][start:start + len(v)] = v
        self.close()
        return arrays

    @property
    def nbytes(self) -> int:
        """Bytes the split's fields take uncompressed in memory."""
        schema = self.manifest["schema"]
        per_record = sum(int(np.prod(schema[k]["shape"], dtype=np.int64)) * np.dtype(schema[k]["dtype"]).itemsize
                         for k in self.fields)
        return per_record * len(self)

    def _file(self, shard: dict[str, Any]):
        import h5py

        if self._pid != os.getpid():  # forked into a DataLoader worker: never share handles
            self._files = OrderedDict()
            self._pid = os.getpid()
        key = shard["file"]
        if key in self._files:
            self._files.move_to_end(key)
            return self._files[key]
        while len(self._files) >= self.max_open:
            _, old = self._files.popitem(last=False)
            old.close()
        f = h5py.File(self.root / key, "r", rdcc_nbytes=1 << 20)
        self._files[key] = f
        return f

    def locate(self, index: int) -> tuple[dict[str, Any], int]:
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(index)
        shard_i = int(np.searchsorted(self.offsets, index, side="right") - 1)
        return self.shards[shard_i], index - int(self.offsets[shard_i])

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        if self.arrays is not None:
            record = {k: v[int(index)] for k, v in self.arrays.items()}  # numpy raises IndexError out of range
        else:
            shard, local = self.locate(int(index))
            f = self._file(shard)
            record = {k: f[k][local] for k in self.fields}
        return self.transform(record) if self.transform else record

    def column(self, name: str) -> np.ndarray:
        """A whole (small, non-image) field of this split, concatenated across shards."""
        if self.arrays is not None and name in self.arrays:
            return self.arrays[name]
        return np.concatenate([np.asarray(self._file(s)[name]) for s in self.shards])

    def shard_arrays(self, fields: list[str] | None = None):
        """Yield each shard of the split as ``{field: array of its records}`` (one shard in memory at a time)."""
        for shard in self.shards:
            f = self._file(shard)
            yield {k: np.asarray(f[k]) for k in (fields or self.fields)}

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_files"] = OrderedDict()
        return state

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
