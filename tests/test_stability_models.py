"""Behaviour of the stability plugin's networks (thesis Section 3.4.1) and augmentations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physint_plugins.stability import augment, model


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """These tests use small tensors; on a shared 2-core machine one intra-op thread is far faster
    (with 2 threads and the other core busy, each small op waited ~100x longer)."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


# --------------------------------------------------------------------------------------------
# models
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [64, 128, 224])
def test_compact_cnn_gives_one_logit_per_image_at_any_size(size):
    m = model.compact_cnn(in_size=size).eval()
    with torch.no_grad():
        out = m(torch.rand(3, 3, size, size))
    assert out.shape == (3,)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()


def test_alexnet_gives_one_logit_per_image():
    m = model.alexnet().eval()
    with torch.no_grad():
        assert m(torch.rand(2, 3, 224, 224)).shape == (2,)
        assert m(torch.rand(1, 3, 96, 96)).shape == (1,)     # adaptive pooling: other sizes work


def test_thin_inception_v4_gives_one_logit_per_image_at_224_and_299():
    m = model.inception_v4(width_multiplier=0.0625).eval()
    with torch.no_grad():
        assert m(torch.rand(2, 3, 224, 224)).shape == (2,)
        assert m(torch.rand(1, 3, 299, 299)).shape == (1,)
    m.train()
    m(torch.rand(2, 3, 96, 96)).sum().backward()             # trains at small sizes too
    assert all(p.grad is not None for p in m.parameters())


def test_parameter_counts_match_the_reference_architectures():
    with torch.device("meta"):                                # shapes only: instant, no memory
        cnn, alex, incp = model.build("cnn"), model.build("alexnet"), model.build("inception-v4")
    assert 300_000 <= model.n_params(cnn) <= 1_000_000  # small enough for a CPU
    assert model.n_params(cnn) == 688_289
    # torchvision's AlexNet has 61,100,840 parameters with 1000 classes; one logit drops 4096·999 + 999
    assert model.n_params(alex) == 61_100_840 - 4097 * 999 == 57_007_937
    # the reference Inception-v4 (tf-slim / timm) has 42,679,816 with 1000 classes; one logit drops 1537·999
    assert model.n_params(incp) == 42_679_816 - 1537 * 999 == 41_144_353


def test_inception_v4_grids_and_blocks_are_those_of_the_paper():
    with torch.device("meta"):
        m = model.inception_v4(in_size=299)
        blocks = list(m.features)
        names = [type(b).__name__ for b in blocks]
        assert names[0] == "_Stem" and names.count("_InceptionC") == 3
        x = m.normalize(torch.empty(1, 3, 299, 299))
        shapes = []
        for b in blocks[:-2]:                                 # up to the adaptive pooling
            x = b(x)
            shapes.append(tuple(x.shape[1:]))
    # stem → 4 × A (35x35x384) → Reduction-A → 7 × B (17x17x1024) → Reduction-B → 3 × C (8x8x1536)
    assert shapes == [(384, 35, 35)] * 5 + [(1024, 17, 17)] * 8 + [(1536, 8, 8)] * 4


def test_build_names_the_models_and_rejects_unknown_ones():
    assert set(model.MODELS) == {"cnn", "alexnet", "inception-v4"}
    assert model.build("cnn", width=8).in_size == 64
    with pytest.raises(ValueError, match="inception-v4"):
        model.build("resnet")
    with pytest.raises(ValueError, match="at least 75"):
        model.inception_v4(in_size=64)


def test_logistic_loss_is_eq_3_2():
    logits, labels = torch.randn(7), torch.randint(0, 2, (7,))
    p = 1 / (1 + torch.exp(-logits))
    eq_3_2 = -(labels * torch.log(p) + (1 - labels) * torch.log(1 - p)).sum()
    assert torch.allclose(model.logistic_loss(logits, labels, reduction="sum"), eq_3_2, atol=1e-5)
    assert torch.allclose(model.logistic_loss(logits.view(7, 1), labels), eq_3_2 / 7, atol=1e-6)


def test_rmsprop_for_uses_the_inception_v4_solver():
    m = model.compact_cnn(width=4)
    opt, sched = model.rmsprop_for(m)
    g = opt.param_groups[0]
    assert isinstance(opt, torch.optim.RMSprop)
    assert (g["lr"], g["alpha"], g["eps"]) == (0.045, 0.9, 1.0)
    lrs = []
    for _ in range(6):                                        # one scheduler step per epoch
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs == pytest.approx([0.045, 0.045, 0.045 * 0.94, 0.045 * 0.94, 0.045 * 0.94**2, 0.045 * 0.94**2])
    opt, _ = model.rmsprop_for(m, paper=False, lr=3e-3)
    assert opt.param_groups[0]["lr"] == 3e-3


def test_adamw_cosine_warms_up_then_decays_to_zero_as_training_ends():
    m = model.compact_cnn(width=4)
    opt, sched = model.adamw_cosine(m, lr=2e-3, weight_decay=0.05, epochs=5)
    assert isinstance(opt, torch.optim.AdamW) and opt.param_groups[0]["weight_decay"] == 0.05
    lrs = []
    for _ in range(6):                                        # one scheduler step per epoch
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(1e-3)                      # warm-up: half the peak in the first epoch
    assert lrs[1] == pytest.approx(2e-3)                      # the peak, then a half cosine
    assert lrs[1] > lrs[2] > lrs[3] > lrs[4] > lrs[5] == pytest.approx(0.0, abs=1e-12)


def _towers(n: int, g: torch.Generator, size: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Three-block 'towers' on random backgrounds; label 1 (unstable) when the top block is shifted
    sideways by 3–5 px.  Both classes have the same colours and block areas, so only the spatial
    arrangement tells them apart."""
    labels = (torch.rand(n, generator=g) < 0.5).long()
    bg, fg = 0.5 * torch.rand(n, 3, generator=g), 0.5 + 0.5 * torch.rand(n, 3, generator=g)
    imgs = bg.view(n, 3, 1, 1) + 0.05 * torch.rand(n, 3, size, size, generator=g)
    block = 6
    for i in range(n):
        x0 = int(torch.randint(8, size - 8 - block, (1,), generator=g))
        shift = int(torch.randint(3, 6, (1,), generator=g)) * (1 if torch.rand(1, generator=g) < 0.5 else -1)
        for level, dx in enumerate((0, 0, shift if labels[i] else 0)):
            top = size - 2 - (level + 1) * block
            imgs[i, :, top:top + block, x0 + dx:x0 + dx + block] = fg[i].view(3, 1, 1)
    return imgs.clamp(0, 1), labels


def test_compact_cnn_learns_a_spatial_stability_task():
    g = torch.Generator().manual_seed(0)
    x_train, y_train = _towers(768, g)
    x_test, y_test = _towers(256, g)
    torch.manual_seed(0)
    m = model.compact_cnn(in_size=32, width=16)
    opt, sched = model.rmsprop_for(m, paper=False)
    for _ in range(6):
        m.train()
        order = torch.randperm(len(x_train))
        for k in range(0, len(order), 32):
            idx = order[k:k + 32]
            loss = model.logistic_loss(m(x_train[idx]), y_train[idx])   # Eq. 3.2
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    m.eval()
    with torch.no_grad():
        accuracy = ((m(x_test) > 0).long() == y_test).float().mean().item()
    assert accuracy >= 0.85


# --------------------------------------------------------------------------------------------
# augmentation
# --------------------------------------------------------------------------------------------

def _images(n: int = 4, h: int = 48, w: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(n, h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize("transform", [augment.TrainTransform(32, seed=0), augment.EvalTransform(32)])
def test_transforms_give_float_chw_images_in_unit_range(transform):
    batch = transform(_images())
    single = transform(torch.as_tensor(_images(1)[0]))
    assert batch.shape == (4, 3, 32, 32) and single.shape == (3, 32, 32)
    for x in (batch, single):
        assert x.dtype == torch.float32 and x.min() >= 0 and x.max() <= 1


def test_eval_transform_only_converts_and_resizes():
    img = _images(1, 32, 32)[0]
    assert torch.equal(augment.EvalTransform(32)(img), torch.as_tensor(img).permute(2, 0, 1).float() / 255)
    assert torch.allclose(augment.TrainTransform(32, strength=0)(img), augment.EvalTransform(32)(img), atol=1e-6)


def test_train_transform_is_deterministic_with_a_seed():
    imgs = _images()
    a = augment.TrainTransform(32, seed=7)(imgs)
    b = augment.TrainTransform(32, generator=torch.Generator().manual_seed(7))(imgs)
    c = augment.TrainTransform(32, seed=8)(imgs)
    assert torch.equal(a, b)
    assert not torch.allclose(a, c)
    t = augment.TrainTransform(32, seed=7)
    assert not torch.allclose(t(imgs), t(imgs))               # a fresh draw on every call


def test_flip_lr_mirrors_columns_not_rows():
    x = torch.zeros(3, 8, 10)
    x[:, 1, 2] = 1.0                                          # a dot near the top-left
    y = augment.flip_lr(x)
    assert y[:, 1, 10 - 1 - 2].eq(1).all() and y.sum() == x.sum()   # same row, mirrored column
    assert torch.equal(augment.flip_lr(y), x)
    batch = augment.to_float(_images())
    assert torch.equal(augment.flip_lr(batch), batch.flip(-1))
    # the training transform's flip is the same mirror
    only_flip = augment.TrainTransform((48, 40), seed=0, p_flip=1.0, brightness=0, contrast=0, saturation=0,
                                       hue=0, channel_shift=0, aspect=0, crop=0, rotate_deg=0)
    assert torch.allclose(only_flip(_images()), augment.flip_lr(batch), atol=1e-4)


def test_augmentation_keeps_towers_upright():
    with pytest.raises(ValueError, match="upright"):
        augment.rotate(torch.rand(3, 16, 16), max_degrees=30)
    assert augment.TrainTransform(32, strength=10).rotate_deg <= augment.MAX_ROTATION_DEG
    # a dark top half (sky) over a bright bottom half (floor) stays so under every augmentation
    img = np.full((16, 32, 32, 3), 230, dtype=np.uint8)
    img[:, :16] = 25
    out = augment.TrainTransform(32, strength=1.5, seed=0)(img)
    top, bottom = out[:, :, :12].mean(dim=(1, 2, 3)), out[:, :, 20:].mean(dim=(1, 2, 3))
    assert (bottom > top + 0.3).all()


def test_individual_augmentations_keep_shape_dtype_and_range():
    x = augment.to_float(_images())
    g = torch.Generator().manual_seed(0)
    for f in (augment.colour_jitter, augment.change_aspect, augment.random_crop, augment.rotate):
        y = f(x, generator=g)
        assert y.shape == x.shape and y.dtype == torch.float32 and 0 <= y.min() and y.max() <= 1
        assert f(x[0], generator=g).shape == x[0].shape
        assert not torch.allclose(y, x)


def test_colour_jitter_is_the_documented_steps_in_one_pass():
    """Brightness, contrast (towards the mean grey), saturation (towards the pixel's grey), a hue
    rotation about the grey axis and channel shifts, one after the other, give what colour_jitter
    gives in one affine pass (mid-grey images, so no step clamps)."""
    x = 0.35 + 0.3 * torch.rand(5, 3, 12, 10, generator=torch.Generator().manual_seed(1))
    kw = dict(brightness=0.2, contrast=0.2, saturation=0.3, hue=0.05, channel_shift=0.02)
    got = augment.colour_jitter(x, generator=torch.Generator().manual_seed(3), **kw)
    g = torch.Generator().manual_seed(3)                       # the same draws, in the same order
    b, c, s = (1 + (2 * torch.rand(5, generator=g) - 1) * kw[k] for k in ("brightness", "contrast", "saturation"))
    h = (2 * torch.rand(5, generator=g) - 1) * kw["hue"] * 2 * math.pi
    shift = ((2 * torch.rand(15, generator=g) - 1) * kw["channel_shift"]).view(5, 3, 1, 1)
    luma = torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
    y = x * b.view(5, 1, 1, 1)
    m = (y * luma).sum(1, keepdim=True).mean(dim=(2, 3), keepdim=True)
    y = (y - m) * c.view(5, 1, 1, 1) + m
    grey = (y * luma).sum(1, keepdim=True)
    y = (y - grey) * s.view(5, 1, 1, 1) + grey
    k = torch.full((3,), 1 / math.sqrt(3))
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    for i in range(5):   # Rodrigues rotation by h about the grey axis
        R = math.cos(h[i]) * torch.eye(3) + math.sin(h[i]) * K + (1 - math.cos(h[i])) * torch.outer(k, k)
        y[i] = torch.einsum("ij,jhw->ihw", R, y[i])
    y = y + shift
    assert 0 < y.min() and y.max() < 1
    assert torch.allclose(got, y, atol=1e-5)


def test_a_checkpoint_whose_layers_do_not_fit_the_model_is_refused_clearly(tmp_path):
    """A predictor saved by a version with other layers: one clear error (exit 2), not a traceback."""
    from physint_cli.errors import BadInput
    from physint_cli.runs import Run
    from physint_cli.training import load_trained_model, save_checkpoint

    path = Run(tmp_path).checkpoint("best")
    path.parent.mkdir(parents=True)
    meta = {"method": "stability", "model": "cnn", "kwargs": {"in_size": 32, "width": 8}}
    older = model.compact_cnn(32, 8).state_dict()
    older = {k.replace("features.1.", "features.9."): v for k, v in older.items()}   # a layer moved
    save_checkpoint(path, model=older, meta=meta)
    with pytest.raises(BadInput, match="does not fit this version's 'cnn' model"):
        load_trained_model(tmp_path, "stability", "stability predictor")
    save_checkpoint(path, model=model.compact_cnn(32, 8).state_dict(), meta=meta)
    net, meta = load_trained_model(tmp_path, "stability", "stability predictor")
    assert meta["kwargs"]["width"] == 8 and not net.training
