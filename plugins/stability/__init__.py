"""stability: ShapeStacks (thesis Chapter 3, Groth et al., ECCV 2018).

A visual classifier learns from images whether a single-stranded stack of shapes will stand,
and is then used, with no physics engine in the loop, to localise instabilities, rank objects by
stackability, build tall stacks and place counterweights. This module holds the hook
implementations only; the chapter is told by the other modules:

    config.py    the config and its tiny / small / paper presets
    physics.py   Lemma 1 (Eq. 3.1) and the violation types VCOM and VPSF
    scenes.py    ShapeStacks scenarios and their backend-neutral scenes
    dataset.py   generating the dataset (Section 3.3, Table 3.1)
    model.py     the predictors: compact CNN, AlexNet, Inception-v4 (Eq. 3.2)
    augment.py   physically plausible augmentation
    train.py     training (Section 3.4.1)
    evaluate.py  accuracy (Table 3.3) and instability localisation (Section 3.4.2, Table 3.4)
    deploy/      stackability, stacking, counterbalancing (Section 3.5), a module each
"""

from physint_cli import hookimpl
from physint_cli.registry import MetricInfo, ModelInfo, SceneInfo


@hookimpl
def register_methods(register):
    from .method import Stability

    register(Stability())


def _stack_builder(subset: str):
    def build(seed: int, **settings):
        from .scenes import build_stack_scene

        return build_stack_scene(subset, seed, **settings)

    return build


@hookimpl
def register_scenes(register):
    # build(seed, height=None, kind="stable", cameras=6, resolution=128) -> (Scene, Scenario): reusable by other plugins
    for name, description in (("cubes", "stacks of regular cubes (ShapeStacks Cubes)"),
                              ("ccs", "stacks of cuboids, cylinders and spheres (ShapeStacks CCS)"),
                              ("all", "both subsets (the thesis's test set)")):
        register(SceneInfo(name, method="stability", build=_stack_builder(name), description=description))


@hookimpl
def register_models(register):
    from . import model

    register(ModelInfo("cnn", method="stability", build=model.compact_cnn,
                       description="compact CNN, the CPU default (0.69M parameters)"))
    register(ModelInfo("alexnet", method="stability", build=model.alexnet,
                       description="AlexNet (Krizhevsky et al. 2012), the thesis's baseline"))
    register(ModelInfo("inception-v4", method="stability", build=model.inception_v4,
                       description="Inception-v4 (Szegedy et al. 2017), the thesis's reference model"))


@hookimpl
def register_metrics(register):
    from .evaluate import accuracy_table
    from .physics import lemma1_side_view

    register(MetricInfo("stability_accuracy", method="stability", fn=accuracy_table,
                        description="accuracy overall and per subset, height and violation type (Table 3.3)"))
    register(MetricInfo("lemma1_side_view", method="stability", fn=lemma1_side_view,
                        description="Lemma 1 (Eq. 3.1) on a tower seen side-on: blocks bottom up as (centre, width, "
                                    "height) along an image's axes; the stack's label as a dict (relate's towers)"))
