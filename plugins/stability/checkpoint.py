"""Loading what train.py saved: the trained stability predictor of a run.

Evaluation and deployment read it through this module, never through train.py.
"""

from __future__ import annotations


def load_predictor(run_dir, device: str = "cpu"):
    """The best checkpoint of a trained stability run, in eval mode, with its input size."""
    from physint_cli.training import load_trained_model

    model, meta = load_trained_model(run_dir, "stability", "stability predictor", device)
    return model, int(meta["kwargs"]["in_size"])
