"""Training RELATE adversarially (thesis Section 5.3.3, Appendix 5.D.1).

Per iteration one discriminator step, then ``train.g_steps`` generator steps, each on freshly sampled
scene latents (Section 5.3.1):

* D: the GAN loss on a batch of real frames and a batch of generated ones, a style loss per
  intermediate layer on the same images, and (arms with the position loss) the position regressor P
  on generated images of one object and the background, towards that object's pose (stop-gradient);
* G (with Psi_b, Psi_f and Gamma): the non-saturating GAN loss and the same position loss, now through
  the generator, so an object has to appear where its pose says (L_tot of Section 5.3.3).

A checkpoint every ``train.checkpoint_every`` updates holds both networks, both optimisers and the
random state: ``--resume`` continues where an interrupted run stopped.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from torch.nn import functional as F

from physint_cli.errors import BadInput
from physint_cli.method import Context

from .checkpoint import dataset_header, real_frames, sample_grid, to_unit
from .dataset import load_split
from .model import Relate, present_mask

MODEL = "relate"
THESIS_SETTINGS = {  # Table 5.D.1 (N_f, N_b, beta1, composition, pose range) per scene family
    "balls-in-bowl": {"z_obj": 1, "z_bg": 3, "beta1": 0.5, "compose": "sum", "fixed_objects": True,
                      "pose_range": (-0.8, 0.8, -0.8, 0.8), "window": 0.5},
    "clevr-table": {"z_obj": 64, "z_bg": 1, "beta1": 0.0, "compose": "max", "fixed_objects": False,
                    "pose_range": (-0.6, 0.6, -0.6, 0.6), "window": 0.25},
    "shapestacks": {"z_obj": 64, "z_bg": 12, "beta1": 0.0, "compose": "max", "fixed_objects": False,
                    "pose_range": (-0.6, 0.6, 0.0, 0.6), "window": 0.25},
}


LEAD = 4  # video: clips start at a random one of the first LEAD + 1 rolled-out frames (the released code: 20 - T)


def model_kwargs(cfg, scene: str, objects: int, frames: int) -> dict[str, Any]:
    """The network's constructor arguments: the config, with the thesis's per-scene values where it says 0 / -1.
    ``frames``: the dataset's frames per record (a video model's clips come from sequences)."""
    thesis = THESIS_SETTINGS[scene]
    if cfg.variant == "ordered" and scene != "shapestacks":
        raise BadInput(f"train.variant=ordered stacks blocks (Eq. 5.3): it needs a shapestacks dataset, not {scene} "
                       "(physint dataset relate --scene shapestacks)")
    if cfg.variant == "video":
        if frames < cfg.clip:
            raise BadInput(f"train.variant=video needs sequences of at least train.clip ({cfg.clip}) frames; this "
                           f"{scene} dataset has {frames} per record (make one with --scene balls-in-bowl)")
        if cfg.arm == "blockgan2d":
            raise BadInput("train.variant=video rolls the poses forward with Gamma: train.arm=blockgan2d has none "
                           "(choose full, no-residual or no-position)")
    if cfg.size % cfg.grid or (cfg.size // cfg.grid) & (cfg.size // cfg.grid - 1):
        raise BadInput(f"train.size ({cfg.size}) must be the feature grid train.grid ({cfg.grid}) times a power of 2")
    if cfg.size % 4 or (cfg.size // 4) & (cfg.size // 4 - 1):
        raise BadInput(f"train.size ({cfg.size}) must be 4 times a power of 2 (16, 32, 64, 128, ...): the "
                       "discriminator halves it down to 4x4")
    share = cfg.window or thesis["window"]
    window = max(2 - cfg.grid % 2, 2 * round((share * cfg.grid - cfg.grid % 2) / 2) + cfg.grid % 2)  # centred: grid - window even
    return {"arm": cfg.arm, "size": cfg.size, "grid": cfg.grid, "window": window,
            "z_obj": cfg.z_obj or thesis["z_obj"], "z_bg": cfg.z_bg or thesis["z_bg"], "channels": cfg.channels,
            "d_channels": cfg.d_channels, "objects": objects, "fixed_objects": thesis["fixed_objects"],
            "compose": thesis["compose"], "pose_range": tuple(cfg.pose_scale * r for r in thesis["pose_range"]), "variant": cfg.variant,
            "clip": cfg.clip if cfg.variant == "video" else 1, "max_speed": cfg.max_speed, "scale": cfg.scale,
            "background_grid": cfg.background_grid or None}


def one_object(present: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """(B, K) one-hot: a random present object per scene (the position loss's single-object image)."""
    weights = present.float() + 1e-9
    pick = torch.multinomial(weights, 1, generator=generator).squeeze(1)
    return F.one_hot(pick, present.shape[1]).bool()


def bce(logits: torch.Tensor, target: float) -> torch.Tensor:
    return F.binary_cross_entropy_with_logits(logits, torch.full_like(logits, target))


class Trainer:
    """The adversarial updates of one RELATE model."""

    def __init__(self, model: Relate, cfg, beta1: float, counts: tuple[int, int], seed: int):
        self.model, self.cfg, self.counts = model, cfg, counts
        g, d = model.generator, model.discriminator
        self.opt_g = torch.optim.Adam(g.parameters(), lr=cfg.lr, betas=(beta1, 0.999))
        self.opt_d = torch.optim.Adam(d.parameters(), lr=cfg.lr, betas=(beta1, 0.999))
        self.rng = torch.Generator().manual_seed(seed)  # scene latents
        self.order = torch.Generator().manual_seed(seed + 1)  # which real frames

    def latents(self, batch: int) -> dict[str, torch.Tensor]:
        g = self.model.generator
        present = present_mask(batch, *self.counts, g.objects, self.rng)
        return g.sample(batch, present=present, generator=self.rng)

    def generate(self, latents) -> tuple[torch.Tensor, torch.Tensor]:
        """Generated images (B, 3, H, W) and poses (B, K, 2); for the video model clips flattened to the
        discriminator's (B, 3 T, H, W), each a random window of a rollout, and their poses (B, T, K, 2)."""
        g, clip = self.model.generator, self.model.clip
        if not g.video:
            return g(latents)
        rollout = g.poses(latents, frames=clip + LEAD)
        start = torch.randint(LEAD + 1, (len(rollout),), generator=self.rng)
        frames = start[:, None] + torch.arange(clip)
        theta = rollout[torch.arange(len(rollout))[:, None], frames]  # (B, T, K, 2)
        images, _ = g(latents, theta=theta)
        return images.flatten(1, 2), theta

    def position_loss(self, latents, theta, through_generator: bool) -> torch.Tensor:
        """||stopgrad(theta_k) - P(G(max(Psi_hat_k, Psi_0)))||^2 for one random present object k per scene. The
        video model's P sees that object's first frame repeated over the clip, standing still (Section 5.3.3)."""
        g, d = self.model.generator, self.model.discriminator
        if self.model.variant == "ordered":  # P reads the tower's base off the whole image (Section 5.A.1)
            with torch.set_grad_enabled(through_generator and torch.is_grad_enabled()):
                image, _ = g(latents, theta=theta)
            return F.mse_loss(d.regress(image), theta.detach()[:, 0])
        keep = one_object(latents["present"], self.rng)
        first = theta[:, 0] if theta.dim() == 4 else theta
        with torch.set_grad_enabled(through_generator and torch.is_grad_enabled()):
            single, _ = g(latents, keep=keep, theta=first)
        if self.model.clip > 1:
            single = torch.cat([single, single.detach().repeat(1, self.model.clip - 1, 1, 1)], dim=1)
        target = first.detach()[keep]  # (B, 2)
        return F.mse_loss(d.regress(single), target)

    def step(self, real: torch.Tensor) -> dict[str, float]:
        g, d, cfg = self.model.generator, self.model.discriminator, self.cfg
        use_position = self.model.position_loss and cfg.position_weight > 0
        # discriminator: GAN + style losses (Section 5.3.3), P on generated single objects
        latents = self.latents(len(real))
        with torch.no_grad():
            fake, theta = self.generate(latents)
        logit_real, style_real = d(real)
        logit_fake, style_fake = d(fake)
        loss_d = bce(logit_real, 1.0) + bce(logit_fake, 0.0)
        loss_style = sum((bce(s, 1.0) + bce(f, 0.0) for s, f in zip(style_real, style_fake)), torch.zeros(()))
        loss_pos_d = self.position_loss(latents, theta, through_generator=False) if use_position else torch.zeros(())
        self.opt_d.zero_grad(set_to_none=True)
        (loss_d + loss_style + cfg.position_weight * loss_pos_d).backward()
        self.opt_d.step()
        # generator: non-saturating GAN loss and the position loss through G
        for _ in range(cfg.g_steps):
            latents = self.latents(len(real))
            fake, theta = self.generate(latents)
            logit, _ = d(fake)
            loss_g = bce(logit, 1.0)
            loss_pos = self.position_loss(latents, theta, through_generator=True) if use_position else torch.zeros(())
            self.opt_g.zero_grad(set_to_none=True)
            (loss_g + cfg.position_weight * loss_pos).backward()
            self.opt_g.step()
        d.zero_grad(set_to_none=True)
        return {"loss_d": loss_d.item(), "loss_style": loss_style.item(), "loss_g": loss_g.item(),
                "loss_position": loss_pos.item()}

    def state(self, iteration: int) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "opt_g": self.opt_g.state_dict(), "opt_d": self.opt_d.state_dict(),
                "iteration": iteration, "rng": self.rng.get_state(), "order": self.order.get_state(),
                "torch_rng": torch.get_rng_state()}

    def load(self, state: dict[str, Any]) -> int:
        self.model.load_state_dict(state["model"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.opt_d.load_state_dict(state["opt_d"])
        self.rng.set_state(state["rng"])
        self.order.set_state(state["order"])
        torch.set_rng_state(state["torch_rng"])
        return int(state["iteration"])


def train(ctx: Context) -> dict[str, Any]:
    import imageio.v3 as iio

    from physint_cli.checkpoints import load_checkpoint, save_checkpoint

    cfg = ctx.config.train
    header = dataset_header(ctx.data)
    scene, data_cfg = header["scene"], header["config"]["data"]
    slots = int(data_cfg["balls"] if scene == "balls-in-bowl" else data_cfg["max_objects"])
    counts = (slots, slots) if scene == "balls-in-bowl" else (int(data_cfg["min_objects"]), slots)
    frames_per_record = int(data_cfg["frames"]) if scene == "balls-in-bowl" else 1
    kwargs = model_kwargs(cfg, scene, slots, frames_per_record)
    beta1 = cfg.beta1 if cfg.beta1 >= 0 else THESIS_SETTINGS[scene]["beta1"]
    real = real_frames(load_split(ctx.data, "train", ("frames",)), cfg.size)
    clip = kwargs["clip"]
    starts = torch.arange(len(real)).reshape(-1, frames_per_record)[:, :frames_per_record - clip + 1].flatten()
    torch.manual_seed(ctx.seed)
    model = Relate(**kwargs)
    trainer = Trainer(model, cfg, beta1, counts, ctx.seed)
    run = ctx.output()
    start = 0
    last = run.checkpoint("last")
    if ctx.resume and last.is_file():
        state = load_checkpoint(last)
        if state.get("kwargs", kwargs) != kwargs:
            raise BadInput(f"{last} was trained with another model ({state['kwargs']}); resume with its config or "
                           "train into a new --out")
        start = trainer.load(state)
        run.rewind_metrics(start)
        ctx.log(f"resuming at generator update {start} of {cfg.iterations}")
    meta = {"method": "relate", "model": MODEL, "kwargs": kwargs, "dataset": str(ctx.data), "scene": scene,
            "backend": header.get("backend"), "counts": list(counts), "size": cfg.size}
    what = f"{clip}-frame clips" if clip > 1 else "frames"
    ctx.log(f"training RELATE ({cfg.variant}, {cfg.arm}) on {len(starts)} {scene} {what} at {cfg.size} px for "
            f"{cfg.iterations} updates")
    t0, history = time.time(), []
    for iteration in range(start, cfg.iterations):
        first = starts[torch.randint(len(starts), (cfg.batch_size,), generator=trainer.order)]
        batch = real[first[:, None] + torch.arange(clip)].flatten(1, 2)  # (B, 3 T, H, W); T = 1 for still frames
        losses = trainer.step(to_unit(batch))
        done = iteration + 1
        if done % 25 == 0 or done == cfg.iterations:
            run.log_metrics(done, **losses)
            history.append({"iteration": done, **losses})
        if done % cfg.samples_every == 0 or done == cfg.iterations:
            iio.imwrite(run.artifact(f"samples_{done:06d}.png"), sample_grid(model, seed=ctx.seed))
        if done % cfg.checkpoint_every == 0 or done == cfg.iterations:
            save_checkpoint(last, **trainer.state(done), kwargs=kwargs, meta=meta)
            if done % (10 * cfg.checkpoint_every) == 0:
                ctx.log(f"update {done}/{cfg.iterations}: " + ", ".join(f"{k} {v:.3f}" for k, v in losses.items()))
    seconds = time.time() - t0
    summary = {"arm": cfg.arm, "scene": scene, "train_frames": int(len(real)), "iterations": cfg.iterations,
               "seconds": round(seconds, 1), "final_losses": history[-1] if history else None}
    run.save_trained(model=model.state_dict(), meta={**meta, "summary": summary})
    return summary


__all__ = ["train"]
