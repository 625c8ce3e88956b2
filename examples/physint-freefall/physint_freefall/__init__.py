"""physint-freefall: a third-party physint plugin. This module holds only the hook implementations:
what the plugin registers. The method itself lives in method.py, its networks in models.py."""

from physint_cli import hookimpl
from physint_cli.registry import ModelInfo, SceneInfo


@hookimpl
def register_methods(register):
    from .method import FreeFall

    register(FreeFall())


def _drop_scene(seed: int, **settings):
    from .method import sample_drop_scene

    return sample_drop_scene(seed, **settings)


@hookimpl
def register_scenes(register):
    # build(seed, image_size=32) -> a backend-neutral Scene: other plugins can drop things too
    register(SceneInfo("drop", method="freefall", build=_drop_scene,
                       description="one sphere or box dropped from rest onto the ground"))


@hookimpl
def register_models(register):
    from . import models

    register(ModelInfo("mlp", method="freefall", build=models.TimeToGroundMLP,
                       description="MLP from drop height to time to ground"))
    # an extra model for a method this plugin does not own: the built-in stability predictor
    register(ModelInfo("pixel-mlp", method="stability", build=models.PixelMLP,
                       description="MLP on downsampled pixels: a weak baseline stability classifier"))


@hookimpl
def register_metrics(register):
    from physint_cli.registry import MetricInfo

    from .method import analytic_time, mean_absolute_error

    register(MetricInfo("mae", method="freefall", fn=mean_absolute_error, description="mean absolute error in seconds"))
    register(MetricInfo("analytic_time", method="freefall", fn=analytic_time, description="sqrt(2h/g)"))


@hookimpl
def register_commands(app):
    import typer

    @app.command("freefall-table")
    def freefall_table(heights: list[float] = typer.Argument(..., help="Drop heights in metres.")):
        """Print the analytic time to ground sqrt(2h/g) for each height."""
        from .method import analytic_time

        for h in heights:
            typer.echo(f"{h:g} m -> {float(analytic_time(h)):.4f} s")
