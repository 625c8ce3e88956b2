"""geeco: goal-conditioned end-to-end visuomotor control (thesis Chapter 6, Groth et al., ICRA 2021).

A controller sees a buffer of its last camera frames and one target image of how the table
should look, and commands end-effector motions and the gripper to push or carry the right cube
onto the right pad: no demonstration or fine-tuning for the new task. This module holds the hook
implementations only; the chapter is told by the other modules:

    method.py      the Method: physint's four verbs, in the modules below
    config.py      the config and its tiny / small / paper presets (Appendix 6.A)
    scenes.py      GOAL2CUBE2, GOAL1CUBE1 and the transfer scenes (Figs. 6.4.1, 6.4.2)
    expert.py      the scripted expert that records the demonstrations
    dataset.py     recording demonstrations (Section 6.4)
    dynamic.py     dynamic images (Eqs. 6.1, 6.2)
    model.py       GEECO-F, -D, -R and E2EVMC; the loss of Eq. 6.3
    episode.py     the one episode loop: who acts (expert, controller, DAgger's mix), what is recorded
    control.py     closed-loop control and the REACH / PICK / PUSH / PLACE outcomes
    train.py       training on demonstration windows
    dagger.py      DAgger rounds for the push controller (not in the thesis)
    checkpoint.py  loading a trained controller and a dataset's start states (eval, deploy, DAgger)
    evaluate.py    success rates with confidence intervals (Tables 6.4.1, 6.4.2, 6.C.1)
    deploy.py      running a controller on a target image or a goal in words
"""

from physint_cli import hookimpl
from physint_cli.registry import ModelInfo, SceneInfo


@hookimpl
def register_methods(register):
    from .method import Geeco

    register(Geeco())


@hookimpl
def register_scenes(register):
    for name, text in (("goal2cube2", "two cubes, two pads, four tasks: the task comes from the target image"),
                       ("goal1cube1", "one cube, one pad (unambiguous: the E2EVMC baseline)"),
                       ("clutter", "GOAL2CUBE2 with distractor objects (FG:CLUTTER, evaluation only)"),
                       ("prisma", "GOAL2CUBE2 before a looping rainbow video (BG:PRISMA, evaluation only)"),
                       ("nutoncone", "drop a hexagonal nut over a cone (evaluation only)"),
                       ("ballincup", "drop a ball into a cup (evaluation only)")):
        register(SceneInfo(name, method="geeco", description=text))


def _builder(variant: str):
    def build(**settings):
        """``Geeco(variant, **settings)``: image_size, width, norm, min_side, stem_stride, dee_bins, dee_modes,
        readout."""
        from .model import Geeco

        return Geeco(variant, **settings)

    return build


@hookimpl
def register_models(register):
    for variant, text in (("geeco-f", "GEECO-F: dynamic images of the buffer and of the difference to the target"),
                          ("geeco-d", "GEECO-D: dynamic difference to the target, buffer fed frame by frame"),
                          ("geeco-r", "GEECO-R: residual target features psi(I_T) - psi(I_t)"),
                          ("e2evmc", "E2EVMC (James et al. 2017): unconditioned baseline")):
        register(ModelInfo(variant, method="geeco", build=_builder(variant), description=text))
