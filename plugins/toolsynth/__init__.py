"""toolsynth: task-driven tool imagination (thesis Chapter 4, Wu, Kasewa, Groth et al., ICML 2020 workshop).

A tool's images are encoded into a latent z_T that a mesh decoder turns back into a 3D mesh; a
classifier on z_T and a task image's latent z_G predicts whether the tool can reach the task's
target. Imagination then descends the classifier's loss in z_T from a tool that cannot, and
decodes the tool that can. This module holds the hook implementations only; the chapter is told
by the other modules:

    method.py       the Method: physint's four verbs, in the modules below
    config.py       the config and its tiny / small / paper presets, and the deviations from the thesis
    tasks.py        the reaching tasks and scenario types A-E (Appendix 4.A, Fig. 4.A.1)
    tools.py        sticks and hooks: footprints, meshes, convex parts (Appendix 4.A)
    feasibility.py  the geometric applicability check that labels tools and judges imagined ones
    scenes.py       tasks and tools as backend-neutral scenes; the simulator's contact check
    dataset.py      the dataset of controlled reaching scenarios (Table 4.A.1)
    softras.py      a differentiable soft silhouette rasteriser (S. Liu et al.)
    model.py        tool encoder psi, mesh decoder psi', task encoder phi, classifier (4.3, 4.B)
    train.py        the curriculum: reconstruction, then task-driven and task-unaware (4.4.2)
    hard.py         hard examples: imagined tools labelled by the geometric check (a deviation)
    checkpoint.py   loading the trained models and a dataset's records (for evaluate and deploy)
    imagine.py      tool imagination by gradient descent in z_T, and the random walk (Eq. 4.5)
    evaluate.py     imagination against its baselines on the test tasks (Table 4.1)
    deploy.py       imagining a tool for one task: mesh, strip, video, rerun, the tool in the simulator
"""

from physint_cli import hookimpl
from physint_cli.registry import ModelInfo, SceneInfo


@hookimpl
def register_methods(register):
    from .method import Toolsynth

    register(Toolsynth())


def _build_task_scene(seed: int, type: str = "A", size: int = 128):
    """``build(seed, type="A", size=128) -> (Scene, Task)``: one task of a scenario type, seen from above
    by the ``task`` camera (the tool is not in it)."""
    import numpy as np

    from . import scenes
    from .tasks import parse_types, sample_task

    (kind,) = parse_types(type, "type")[:1]
    task = sample_task(kind, np.random.default_rng(seed))
    from physint_backends.spec import Scene

    return Scene(bodies=scenes.task_bodies(task), cameras=[scenes.task_camera(size)], ground=None,
                 background=scenes.BACKGROUND), task


@hookimpl
def register_scenes(register):
    register(SceneInfo("reaching", method="toolsynth", build=_build_task_scene,
                       description="top-down reaching tasks of scenario types A-E with a stick or hook"))


def _build_toolsynth(**kwargs):
    from .model import ToolSynth

    return ToolSynth(**kwargs)


@hookimpl
def register_models(register):
    register(ModelInfo("toolsynth", method="toolsynth", build=_build_toolsynth,
                       description="psi, psi' (icosphere mesh decoder), phi and the classifier of Fig. 4.3"))
