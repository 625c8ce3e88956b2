"""relate: RELATE, physically plausible multi-object scene synthesis (thesis Chapter 5, Ehrhardt, Groth et al.,
NeurIPS 2020).

A GAN whose latent space is a background and one appearance and one pose per object. A relationship
module Gamma corrects each object's independently drawn pose from its pairwise interactions with the
others, so that the generated scenes are physically plausible (balls stay in their bowl, objects do not
overlap). The objects' features are placed at their poses, composed, and rendered into the image. This
module holds the hook implementations only; the chapter is told by the other modules:

    method.py    the Method: physint's four verbs, in the modules below
    config.py    the config and its tiny / small / paper presets, and the deviations from the thesis
    scenes.py    balls-in-bowl, clevr-table and shapestacks (through the stability plugin) as scenes
    dataset.py   the simulated sequences and images with their ground truth (Section 5.4)
    model.py     Psi_b, Psi_f, Gamma (Eqs. 5.1, 5.2), the renderer G, the discriminator and P (5.3, 5.D)
    train.py     the adversarial training with the style and position losses (Section 5.3.3)
"""

from physint_cli import hookimpl
from physint_cli.registry import ModelInfo, SceneInfo


@hookimpl
def register_methods(register):
    from .method import Relate

    register(Relate())


@hookimpl
def register_scenes(register):
    for name, text in (("balls-in-bowl", "two balls rolling in an elliptical bowl, from above (sequences)"),
                       ("clevr-table", "2-5 CLEVR-like primitives on a table, in perspective"),
                       ("shapestacks", "ShapeStacks towers of 2-5 blocks (the stability plugin's), for the ordered variant")):
        register(SceneInfo(name, method="relate", description=text))


def _build_relate(**kwargs):
    from .model import Relate

    return Relate(**kwargs)


@hookimpl
def register_models(register):
    register(ModelInfo("relate", method="relate", build=_build_relate,
                       description="RELATE's generator (Psi_b, Psi_f, Gamma, G) and discriminator with P (Fig. 5.3.1)"))
