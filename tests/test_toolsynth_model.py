"""Behaviour of toolsynth's soft rasteriser and networks (thesis Section 4.3, Appendix 4.B)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

import physint_backends as pb
from physint_backends import Body, Camera, Scene
from physint_plugins.toolsynth import model, softras


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small tensors on a shared 2-core machine: one intra-op thread is faster."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


def orbit(views: int = 4, size: int = 64, radius: float = 0.9, elevation: float = 30.0) -> list[Camera]:
    el = math.radians(elevation)
    return [Camera(f"view{k}", pos=(radius * math.cos(el) * math.cos(az), radius * math.cos(el) * math.sin(az),
                                    radius * math.sin(el)), lookat=(0.0, 0.0, 0.0), fovy=40.0, width=size, height=size)
            for k, az in enumerate(2 * math.pi * (np.arange(views) + 0.3) / views)]


def mesh_tensors(mesh: trimesh.Trimesh, batch: int = 1, dtype=torch.float32):
    v = torch.tensor(np.asarray(mesh.vertices), dtype=dtype).expand(batch, -1, -1).contiguous()
    return v, torch.tensor(np.asarray(mesh.faces), dtype=torch.long)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


# --------------------------------------------------------------------------------------------
# the rasteriser
# --------------------------------------------------------------------------------------------

def test_project_matches_camera_project():
    cams = orbit(5) + [Camera("top", pos=(0.0, 0.0, 1.2), up=(0.0, 1.0, 0.0), fovy=40.0)]
    tensors = softras.camera_tensors(cams)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.3, 0.3, (len(cams), 50, 3))
    pixels, depth = softras.project(torch.tensor(points, dtype=torch.float32), tensors, torch.arange(len(cams)),
                                    return_depth=True)
    for k, cam in enumerate(cams):
        np.testing.assert_allclose(pixels[k].numpy(), cam.project(points[k]), atol=1e-4)
        assert (depth[k] > 0.3).all()
    with pytest.raises(ValueError, match="one image size"):
        softras.camera_tensors([Camera("a", width=32, height=32), Camera("b")])


def test_soft_box_silhouette_matches_mujoco_segmentation():
    size = (0.06, 0.4, 0.02)
    cams = orbit(4) + [Camera("top", pos=(0.0, 0.0, 1.2), up=(0.0, 1.0, 0.0), fovy=40.0)]
    scene = Scene(bodies=[Body.box("tool", size, static=True)], cameras=cams, ground=None)
    with pb.make("mujoco", scene) as sim:
        masks = [sim.render(c.name, rgb=False, segmentation=True).segmentation == 0 for c in cams]
    v, faces = mesh_tensors(trimesh.creation.box(extents=size), len(cams))
    tensors = softras.camera_tensors(cams)
    sil = softras.soft_silhouette(softras.project(v, tensors, torch.arange(len(cams))), faces, 64, 64, sigma=0.05)
    for cam, mask, soft in zip(cams, masks, sil.numpy()):
        assert mask.sum() > 30, cam.name
        assert iou(soft > 0.5, mask) > 0.9, cam.name
    # the soft IoU loss against the simulator's masks is small too
    assert softras.iou_loss(sil, torch.tensor(np.stack(masks), dtype=torch.float32)).item() < 0.15


def test_soft_silhouette_matches_dense_reference_values_and_gradients():
    """Culling, tiling, chunking and the analytic backward change nothing beyond the culled terms."""
    torch.manual_seed(0)
    cams = softras.camera_tensors(orbit(3, size=20), dtype=torch.float64)
    v, faces = mesh_tensors(trimesh.creation.icosphere(subdivisions=1, radius=0.15), 3, torch.float64)
    v = (v + 0.03 * torch.randn_like(v)).requires_grad_()
    weights = torch.rand(3, 20, 20, dtype=torch.float64)
    for sigma, chunk, tile in ((1.0, 1 << 18, 4), (0.3, 200, 8), (2.0, 64, 3)):
        fast = softras.soft_silhouette(softras.project(v, cams, torch.arange(3)), faces, 20, 20, sigma, chunk=chunk,
                                       tile=tile)
        dense = softras._dense_silhouette(softras.project(v, cams, torch.arange(3)), faces, 20, 20, sigma)
        assert (fast - dense).abs().max() < 1e-5
        g_fast, = torch.autograd.grad((fast * weights).sum(), v)
        g_dense, = torch.autograd.grad((dense * weights).sum(), v)
        assert (g_fast - g_dense).abs().max() < 1e-3 * g_dense.abs().max()


def test_soft_silhouette_covers_inside_and_fades_outside():
    tri = torch.tensor([[[4.0, 4.0], [28.0, 4.0], [4.0, 28.0]]])  # one triangle, either winding
    for pixels in (tri, tri[:, [0, 2, 1]]):
        sil = softras.soft_silhouette(pixels, torch.tensor([[0, 1, 2]]), 32, 32, sigma=1.0)[0]
        assert sil.min() >= 0 and sil.max() <= 1
        assert sil[8, 8] > 0.999 and sil[30, 30] < 1e-6  # well inside, well outside
        assert sil[3, 10].item() == pytest.approx(1 / (1 + math.exp(0.25)), abs=1e-6)  # 0.5 px outside y = 4
        assert sil[4, 10].item() == pytest.approx(1 / (1 + math.exp(-0.25)), abs=1e-6)  # 0.5 px inside
    empty = softras.soft_silhouette(tri + 1000, torch.tensor([[0, 1, 2]]), 32, 32)
    assert empty.abs().max() == 0


def test_iou_loss():
    a = torch.zeros(2, 8, 8)
    a[:, :4] = 1
    assert softras.iou_loss(a, a).item() == pytest.approx(0.0, abs=1e-5)
    assert softras.iou_loss(a, 1 - a).item() == pytest.approx(1.0)
    b = a.clone()
    b[:, 4:6] = 1
    assert softras.iou_loss(a, b).item() == pytest.approx(1 - 32 / 48, abs=1e-5)


def test_free_decoder_crosses_the_centre_inside_the_extent():
    torch.manual_seed(0)
    dec = model.MeshDecoder(z_tool=8, subdivisions=1, extent=0.3, hidden=(32, 64), deform="free")
    with torch.no_grad():
        for head in (dec.offsets, dec.centroid):
            head.weight.zero_()
    assert torch.allclose(dec(torch.randn(2, 8))[0], dec.template(), atol=1e-5)  # zero heads: the template
    with torch.no_grad():
        dec.offsets.bias.view(-1, 3)[:, 0] = -8.0  # push every vertex to -x
    v = dec(torch.randn(2, 8))
    assert v.abs().max() <= 0.3 + 1e-6 and (v[..., 0] < 0).all()  # all across the centre, as octants forbid
    with pytest.raises(ValueError, match="deform"):
        model.MeshDecoder(z_tool=8, deform="melt")


def test_gradients_through_decoder_and_rasteriser_fit_a_silhouette():
    torch.manual_seed(0)
    cams = orbit(2)
    tensors, index = softras.camera_tensors(cams), torch.arange(2)
    v, faces = mesh_tensors(trimesh.creation.box(extents=(0.04, 0.36, 0.02)), 2)
    target = softras.soft_silhouette(softras.project(v, tensors, index), faces, 64, 64, sigma=0.1).detach()
    decoder = model.MeshDecoder(z_tool=16, hidden=(64, 128)).requires_grad_(False)
    z = torch.zeros(1, 16, requires_grad=True)
    offsets = torch.zeros(1, decoder.vertices_n, 3, requires_grad=True)  # a free deformation of the template
    opt = torch.optim.Adam([z, offsets], lr=0.05)
    losses = []
    for _ in range(100):
        verts = decoder(z) + offsets * 0.1
        sil = softras.soft_silhouette(softras.project(verts.expand(2, -1, -1), tensors, index), decoder.faces,
                                      64, 64, sigma=1.0)
        loss = softras.iou_loss(sil, target) + 1e-3 * model.laplacian_loss(verts / 0.6, decoder.faces)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(softras.iou_loss(sil, target).item())
    assert losses[-1] < 0.5 * losses[0] and losses[-1] < 0.3, (losses[0], losses[-1])


# --------------------------------------------------------------------------------------------
# the networks
# --------------------------------------------------------------------------------------------

def test_every_module_has_the_thesis_shapes_at_64px():
    torch.manual_seed(0)
    m = model.ToolSynth(image_size=64, task_size=64, width=0.25, task_width=0.25)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    sil = rng.integers(0, 2, (3, 64, 64), dtype=np.uint8)
    task = rng.integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    x = model.tool_input(rgb, sil)
    assert x.shape == (3, 4, 64, 64) and x.dtype == torch.float32 and 0 <= x.min() and x.max() <= 1
    assert torch.equal(x[:, 3], torch.tensor(sil, dtype=torch.float32))
    t = model.task_input(task)
    assert t.shape == (3, 3, 64, 64)
    out = m(x, t)
    assert out["z_tool"].shape == (3, 512) and out["z_task"].shape == (3, 256)
    assert out["vertices"].shape == (3, 162, 3) and m.faces.shape == (320, 3)
    assert out["vertices"].abs().max() <= 0.3
    assert out["logits"].shape == (3, 2)
    assert m.task_encoder.side == 2  # the last convolution's kernel at 64 px
    assert torch.allclose(m.encode_tool(torch.as_tensor(rgb), torch.as_tensor(sil)), out["z_tool"])
    assert torch.allclose(m.encode_task(torch.as_tensor(task)), out["z_task"])
    p = model.p_success(out["logits"])
    assert torch.allclose(torch.sigmoid(model.success_logit(out["logits"])), p, atol=1e-6)
    assert torch.isfinite(model.task_loss(out["logits"], torch.tensor([0, 1, 1])))
    # rebuilt from its kwargs (as a checkpoint stores them) it is the same network
    again = model.ToolSynth(**m.kwargs)
    again.load_state_dict(m.state_dict())
    assert torch.allclose(again.eval()(x, t)["logits"], m.eval()(x, t)["logits"])


def test_128px_encoders_keep_the_latents_and_the_maps():
    enc = model.ToolEncoder(image_size=128, z_tool=32, width=0.125, norm="group")
    assert len([c for c in enc.convs if isinstance(c, torch.nn.Conv2d)]) == 4
    assert enc(torch.rand(2, 4, 128, 128)).shape == (2, 32)
    phi = model.TaskEncoder(image_size=128, z_task=256, width=0.25)
    assert phi.side == 4 and phi(torch.rand(2, 3, 128, 128)).shape == (2, 256)  # Appendix 4.B: kernel 4
    assert model.Classifier()(torch.zeros(2, 256), torch.zeros(2, 512)).shape == (2, 2)
    assert model.Classifier().mlp[0].in_features == 768


def test_decoder_keeps_octants_inside_the_extent():
    torch.manual_seed(0)
    dec = model.MeshDecoder(z_tool=8, subdivisions=1, extent=0.3, hidden=(32, 64))
    with torch.no_grad():
        dec.offsets.weight.mul_(100)  # wild offsets
        dec.centroid.weight.mul_(100)
    z = 5 * torch.randn(4, 8)
    v = dec(z)
    assert v.shape == (4, 42, 3) and v.abs().max() <= 0.3 + 1e-6
    c = 0.3 * torch.tanh(dec.centroid(dec.fc(z)) * dec.centroid_scale)[:, None]
    side = torch.sign(v - c)
    assert ((side == dec.sign) | (dec.sign == 0)).all()  # each vertex stays in its octant round the centroid
    # zero offsets draw the (flat) template
    flat = model.MeshDecoder(z_tool=8, hidden=(32, 64))
    with torch.no_grad():
        for head in (flat.offsets, flat.centroid):
            head.weight.zero_()
    v = flat(torch.randn(2, 8))
    assert torch.allclose(v[0], flat.template(), atol=1e-6)
    extent = v[0].amax(0) - v[0].amin(0)
    assert extent[1] > 2 * extent[0] > 4 * extent[2]  # long along y, thin in z


def test_geometry_losses():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    v, faces = mesh_tensors(sphere, 2)
    torch.manual_seed(0)
    bumpy = v + 0.1 * torch.randn_like(v)
    for loss in (model.laplacian_loss, model.flatten_loss):
        smooth, rough = loss(v, faces), loss(bumpy, faces)
        assert torch.isfinite(smooth) and torch.isfinite(rough)
        assert rough > 3 * smooth, loss.__name__
    # a flat grid costs nothing to the flatten loss; folding it in half does
    grid = trimesh.creation.box(extents=(1, 1, 1)).subdivide().subdivide()
    top = grid.vertices[:, 2] > 0.49
    face_top = top[grid.faces].all(1)
    plane = trimesh.Trimesh(grid.vertices, grid.faces[face_top])
    pv, pf = mesh_tensors(plane)
    assert model.flatten_loss(pv, pf).item() < 1e-8
    folded = pv.clone()
    right = folded[..., 0] > 0
    folded[..., 2] = torch.where(right, 0.5 + folded[..., 0], folded[..., 2])  # the right half stands up
    folded[..., 0] = torch.where(right, 0.0 * folded[..., 0], folded[..., 0])
    assert model.flatten_loss(folded, pf).item() > 1.0
    # the assembled Eq. 4.2
    sil = torch.rand(2, 8, 8)
    parts = model.recon_loss(sil, (sil > 0.5).float(), bumpy, faces, 5e-3, 5e-4)
    assert set(parts) >= {"silhouette", "laplacian", "flatten", "total"}
    expected = parts["silhouette"] + 5e-3 * parts["laplacian"] + 5e-4 * parts["flatten"]
    assert torch.allclose(parts["total"], expected)


def test_jitter_scales_with_the_batch_spread_and_is_off_at_zero():
    torch.manual_seed(0)
    z = torch.randn(4096, 8) * torch.tensor([0.1, 1.0, 10.0, 1.0, 1.0, 1.0, 1.0, 1.0]) + 3.0
    assert torch.equal(model.jitter(z, 0.0), z)
    noise = model.jitter(z, 0.5) - z
    ratio = noise.std(dim=0) / (0.5 * z.std(dim=0))  # noise per coordinate follows that coordinate's spread
    assert torch.allclose(ratio, torch.ones(8), atol=0.06)
    assert abs(float(noise.mean())) < 0.05
    z.requires_grad_(True)
    model.jitter(z, 0.5).sum().backward()  # the spread is detached: the gradient to z is the identity's
    assert torch.allclose(z.grad, torch.ones_like(z))


def _hard_batch(tasks, labels):
    from physint_plugins.toolsynth.tasks import MAX_OBSTACLES

    rows = [t.to_arrays() for t in tasks]
    batch = {k: torch.as_tensor(np.stack([r[k] for r in rows])) for k in rows[0]}
    assert batch["obstacles"].shape[1] == MAX_OBSTACLES
    return {**batch, "label": torch.tensor(labels)}


def test_hard_examples_are_labelled_by_the_check_of_the_decoded_tool():
    from physint_plugins.toolsynth.hard import HardExamples
    from physint_plugins.toolsynth.imagine import judge
    from physint_plugins.toolsynth.tasks import Task

    torch.manual_seed(0)
    net = model.ToolSynth(image_size=32, task_size=32, z_tool=16, z_task=8, width=0.25, task_width=0.25,
                          subdivisions=1, deform="free")
    with torch.no_grad():  # a classifier sure of success everywhere: imagination stops at once
        net.classifier.mlp[-1].bias.copy_(torch.tensor([0.0, 10.0]))
    near, far = Task("A", (0.0, -0.19)), Task("A", (0.0, 0.29))  # 3 cm / 51 cm beyond the red line
    z_task, z_tool = torch.randn(6, 8), torch.randn(6, 16)
    # the decoder's near-template plates reach the near target and not the far one
    assert [v.feasible for v in judge(net, z_tool, [near] * 3 + [far] * 3)[0]] == [True] * 3 + [False] * 3
    labels = [0, 1, 0, 0, 1, 0]
    for task, share in ((near, 1.0), (far, 0.0)):
        hard = HardExamples(count=3, steps=5, step=0.01, threshold=0.997, optimizer="adam")
        batch = _hard_batch([task] * 6, labels)
        loss = hard.loss(net, net, z_task, z_tool, batch)
        assert hard.seen == 3 and hard.summary()["hard_feasible"] == share  # infeasible records only, at most 3
        # the hard examples join the records in one mean: 6 records and 3 imagined tools
        logits = net.classify(torch.cat([z_task, z_task[[0, 2, 3]]]), torch.cat([z_tool, z_tool[[0, 2, 3]]]))
        expected = model.task_loss(logits, torch.tensor(labels + [int(share)] * 3))
        assert torch.allclose(loss, expected)
    off = HardExamples(count=0, steps=5, step=0.01, threshold=0.997, optimizer="adam")
    assert torch.allclose(off.loss(net, net, z_task, z_tool, _hard_batch([far] * 6, labels)),
                          model.task_loss(net.classify(z_task, z_tool), torch.tensor(labels)))
    assert off.seen == 0


def test_imagination_stays_in_the_box_of_the_training_latents():
    from physint_plugins.toolsynth.imagine import imagine, latent_box

    torch.manual_seed(0)
    net = model.ToolSynth(image_size=32, task_size=32, z_tool=16, z_task=8, width=0.25, task_width=0.25,
                          subdivisions=1, deform="free")
    records = torch.randn(200, 16)
    low, high = latent_box(records)
    assert torch.equal(low, records.min(0).values) and torch.equal(high, records.max(0).values)
    wide = latent_box(records, margin=0.5)
    assert torch.allclose(wide[1] - wide[0], 2 * (high - low))
    z_task, z0 = torch.randn(8, 8), records[:8]
    for method in ("descent", "random"):
        free = imagine(net, z_task, z0, method, step=0.5, max_steps=50, threshold=0.999999)
        boxed = imagine(net, z_task, z0, method, step=0.5, max_steps=50, threshold=0.999999, box=(low, high))
        assert ((free.z < low) | (free.z > high)).any()  # unbounded, 50 steps of 0.5 leave the box
        assert ((boxed.z >= low) & (boxed.z <= high)).all()
        assert not torch.equal(boxed.z, z0)  # and still moved


def test_a_layer_latent_has_a_fixed_scale_that_weights_cannot_inflate():
    torch.manual_seed(0)
    enc = model.ToolEncoder(image_size=32, z_tool=16, width=0.25, latent="layer")
    x = torch.rand(4, 4, 32, 32)
    z = enc(x)
    with torch.no_grad():
        enc.fc[-1].weight.mul_(100.0)
        enc.fc[-1].bias.mul_(100.0)
    assert torch.allclose(enc(x).pow(2).mean(1), torch.ones(4), atol=1e-3)  # unit spread over coordinates
    assert torch.allclose(enc(x), z, atol=1e-2)  # up to LayerNorm's eps
    assert torch.allclose(z.mean(1), torch.zeros(4), atol=1e-5)
    with pytest.raises(ValueError, match="latent"):
        model.ToolEncoder(image_size=32, z_tool=16, latent="tanh")
