"""The networks of tool imagination (thesis Section 4.3, Fig. 4.2-4.3, Appendix 4.B) and Eq. 4.2's losses.

* :class:`ToolEncoder` psi (Eq. 4.1): z_T = psi(I_T^i, I_S^i), the tool's RGB image and its
  silhouette as four channels. The encoder of S. Liu et al.'s SoftRas reconstruction model (which
  Section 4.3.1 adopts from Kato et al.): 5x5 stride-2 convolutions of 64, 128, 256 filters with
  normalisation and ReLU, down to an 8x8 map (a 128 px image gets a fourth block, of 256), then
  FC 1024, FC 1024 (ReLU) and a linear FC to z_T (512). z_T is left linear, not rectified, so that
  imagination (Eq. 4.5) can move it either way along every axis.
  ``latent="layer"`` standardises z_T over its coordinates (a LayerNorm without weights), so its
  scale is fixed and L_task cannot inflate it (the small preset).
* :class:`MeshDecoder` psi': z_T -> the vertices of a deformed template icosphere. SoftRas's
  decoder: FC 1024, FC 2048 (ReLU), then a centroid c (3) and an offset per vertex coordinate. A
  template coordinate x keeps its sign: it becomes u = sign(x) sigmoid(logit|x| + offset) in
  (-1, 1), so a vertex stays in its octant, and the octants are placed round the centroid
  c = tanh(.) inside the cube [-1, 1]^3 (u > 0 is stretched over [c, 1], u < 0 over [-1, c]);
  the cube is scaled to ``extent`` metres. Template coordinates that are exactly 0 (the icosphere
  has vertices on the coordinate planes) stay on the centroid's planes.
  ``template_scale`` shrinks the template per axis before the logit, which sets the shape the
  decoder draws for zero offsets: SoftRas uses 0.5 on every axis (a sphere of half the cube); the
  default here, ``FLAT_TEMPLATE``, is a flat ellipsoid lying in the x-y plane and long along y,
  as the tools are (sticks and hooks up to 0.5 m along y, a few cm wide, 2 cm thick in z), so
  learning starts from a tool-like plate rather than from a ball most of whose surface has to
  collapse onto a plane. The heads start at a tenth of PyTorch's initial weights, so the first
  meshes are close to the template.
  ``deform="free"`` drops the octants: each coordinate becomes tanh(atanh(x) + offset + c), free
  to cross the centre. An L-shaped hook leaves a quadrant round its bounding box's centre empty
  (below the hook, beside the handle); octant-bound vertices cannot leave it and collapse into a
  thin sheet there, a second leg that the silhouettes hardly see but the top-down outline does.
* :func:`laplacian_loss` and :func:`flatten_loss` make up the geometry loss L_g of Eq. 4.2 (Kato
  et al., S. Liu et al.); :func:`recon_loss` is L_recon = L_s + mu L_g (Eq. 4.2) with L_s the
  silhouette IoU loss of ``softras.iou_loss``.
* :class:`TaskEncoder` phi (Appendix 4.B): five blocks of two 5x5 convolutions (padding 2; stride 1,
  then 2) with 16, 32, 64, 64, 128 filters, and one convolution whose kernel is the remaining map
  (4 at 128 px, 2 at 64 px) to 256 channels, z_G; ELU after every convolution.
* :class:`Classifier` ff (Section 4.3.2, Appendix 4.B): h_cat = [z_G, z_T] (768) -> 1024 -> 512 -> 2
  logits, ELU between; p(success) = softmax(logits)[1]; :func:`task_loss` is Eq. 4.3.

``width`` and ``task_width`` scale the filters of the two encoders (1.0: the thesis) for the CPU
presets. :class:`ToolSynth` holds the four networks; ``ToolSynth(**model.kwargs)`` rebuilds it.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from . import softras

TOOL_FILTERS = (64, 128, 256)  # SoftRas's encoder; further blocks (128 px) keep the last
TOOL_MAP = 8  # side of the tool encoder's last map
TASK_FILTERS = (16, 32, 64, 64, 128)  # Appendix 4.B
FLAT_TEMPLATE = (0.3, 0.75, 0.1)  # template scale per axis: a flat plate along y (SoftRas: 0.5, 0.5, 0.5)
NORMS = ("batch", "group", "none")
DEFORMS = ("octant", "free")
LATENTS = ("linear", "layer")


def _channels(filters: int, width: float) -> int:
    return max(4, int(round(filters * width)))


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":  # up to 8 groups of at least 4 channels, a divisor of ``channels``
        groups = max(1, min(8, channels // 4))
        while channels % groups:
            groups -= 1
        return nn.GroupNorm(groups, channels)
    return nn.Identity()


def tool_blocks(image_size: int) -> int:
    """Stride-2 blocks of the tool encoder: at least SoftRas's three, more until the map is 8x8."""
    blocks, side = len(TOOL_FILTERS), math.ceil(image_size / 2 ** len(TOOL_FILTERS))
    while side > TOOL_MAP:
        blocks, side = blocks + 1, math.ceil(side / 2)
    return blocks


class ToolEncoder(nn.Module):
    """psi (Eq. 4.1): (B, 4, S, S) tool RGB + silhouette in [0, 1] -> z_T (B, z_tool)."""

    def __init__(self, image_size: int = 64, z_tool: int = 512, width: float = 1.0, norm: str = "batch",
                 hidden: int = 1024, latent: str = "linear"):
        super().__init__()
        if norm not in NORMS:
            raise ValueError(f"norm {norm!r} is not known; valid: {', '.join(NORMS)}")
        if latent not in LATENTS:
            raise ValueError(f"latent {latent!r} is not known; valid: {', '.join(LATENTS)}")
        layers: list[nn.Module] = []
        channels, side = 4, image_size
        for i in range(tool_blocks(image_size)):
            out = _channels(TOOL_FILTERS[min(i, len(TOOL_FILTERS) - 1)], width)
            layers += [nn.Conv2d(channels, out, 5, stride=2, padding=2), _norm(norm, out), nn.ReLU(inplace=True)]
            channels, side = out, math.ceil(side / 2)
        self.convs = nn.Sequential(*layers)
        self.fc = nn.Sequential(nn.Linear(channels * side * side, hidden), nn.ReLU(inplace=True),
                                nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, z_tool))
        # "layer": each z_T standardised over its coordinates, so its scale is fixed
        self.out = nn.LayerNorm(z_tool, elementwise_affine=False) if latent == "layer" else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.fc(self.convs(x.contiguous(memory_format=torch.channels_last)).flatten(1)))


class MeshDecoder(nn.Module):
    """psi': z_T (B, z_tool) -> vertices (B, V, 3) in metres, within [-extent, extent]^3."""

    def __init__(self, z_tool: int = 512, subdivisions: int = 2, extent: float = 0.3,
                 template_scale: tuple[float, float, float] = FLAT_TEMPLATE, hidden: tuple[int, int] = (1024, 2048),
                 centroid_scale: float = 0.1, offset_scale: float = 1.0, deform: str = "octant"):
        super().__init__()
        import trimesh

        if deform not in DEFORMS:
            raise ValueError(f"deform {deform!r} is not known; valid: {', '.join(DEFORMS)}")
        self.deform = deform

        if not all(0 < s < 1 for s in template_scale):
            raise ValueError(f"template_scale must lie in (0, 1) on each axis, got {template_scale}")
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
        base = torch.tensor(sphere.vertices, dtype=torch.float32) * torch.tensor(template_scale)
        self.register_buffer("faces", torch.tensor(sphere.faces, dtype=torch.long))
        self.register_buffer("sign", torch.sign(base))
        self.register_buffer("base_logit", torch.logit(base.abs().clamp(1e-4, 1 - 1e-4)))
        self.register_buffer("base_atanh", torch.atanh(base.clamp(-1 + 1e-4, 1 - 1e-4)), persistent=False)
        self.vertices_n = base.shape[0]
        self.extent, self.centroid_scale, self.offset_scale = extent, centroid_scale, offset_scale
        self.fc = nn.Sequential(nn.Linear(z_tool, hidden[0]), nn.ReLU(inplace=True),
                                nn.Linear(hidden[0], hidden[1]), nn.ReLU(inplace=True))
        self.centroid = nn.Linear(hidden[1], 3)
        self.offsets = nn.Linear(hidden[1], self.vertices_n * 3)
        with torch.no_grad():  # start near the template
            for head in (self.centroid, self.offsets):
                head.weight.mul_(0.1)
                head.bias.zero_()

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.fc(z)
        offsets = (self.offsets(h) * self.offset_scale).view(-1, self.vertices_n, 3)
        if self.deform == "free":  # every coordinate free in (-1, 1), shifted by c before the tanh
            return torch.tanh(self.base_atanh + offsets + self.centroid(h)[:, None, :]) * self.extent
        c = torch.tanh(self.centroid(h) * self.centroid_scale)[:, None, :]  # (B, 1, 3) in (-1, 1)
        u = self.sign * torch.sigmoid(self.base_logit + offsets)  # in (-1, 1), the template's octant
        v = c + F.relu(u) * (1 - c) - F.relu(-u) * (1 + c)  # u > 0 over [c, 1], u < 0 over [-1, c]
        return v * self.extent

    def template(self) -> torch.Tensor:
        """The shape drawn for zero offsets and centroid (V, 3), metres."""
        return self.sign * torch.sigmoid(self.base_logit) * self.extent


# -- the geometry loss L_g (Eq. 4.2) --------------------------------------------------------------
_TOPOLOGY: dict = {}


def _topology(faces: torch.Tensor):
    """Neighbours of a triangle mesh, cached per face array: the undirected edges (E, 2) and each
    vertex's degree (V,); and for every edge two faces share, its ends (v0, v1) and the two
    vertices opposite it (a, b), as (I, 4)."""
    key = (faces.device, faces.shape, faces.cpu().numpy().tobytes())
    if key not in _TOPOLOGY:
        f = faces.cpu().numpy().astype(np.int64)
        ends = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # each face's edges
        opposite = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
        ends.sort(axis=1)
        edges, inverse, counts = np.unique(ends, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        order = np.argsort(inverse, kind="stable")
        shared = np.flatnonzero(counts == 2)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[shared]
        hinges = np.column_stack([edges[shared], opposite[order[starts]], opposite[order[starts + 1]]])
        degree = np.bincount(edges.reshape(-1), minlength=int(f.max()) + 1)
        _TOPOLOGY[key] = tuple(torch.as_tensor(a, device=faces.device) for a in (edges, degree, hinges))
    return _TOPOLOGY[key]


def laplacian_loss(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """sum_i |v_i - mean_{j in N(i)} v_j|^2 per mesh (B, V, 3), meaned over the batch."""
    edges, degree, _ = _topology(faces)
    neighbours = torch.zeros_like(vertices)
    neighbours.index_add_(1, edges[:, 0], vertices[:, edges[:, 1]])
    neighbours.index_add_(1, edges[:, 1], vertices[:, edges[:, 0]])
    delta = vertices - neighbours / degree.clamp_min(1).to(vertices.dtype)[None, :, None]
    return delta.pow(2).sum((1, 2)).mean()


def flatten_loss(vertices: torch.Tensor, faces: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """sum over edges shared by two faces of (1 + cos theta)^2 per mesh, meaned over the batch;
    theta is the angle between the two faces at the edge, pi where they lie flat, 0 where one is
    folded back onto the other. The cosine is that of the two faces' heights over the edge: the
    parts of (a - v0) and (b - v0) perpendicular to the edge (v0, v1)."""
    _, _, hinges = _topology(faces)
    v0, v1, a, b = (vertices[:, hinges[:, k]] for k in range(4))
    e = v1 - v0
    e = e / (e.pow(2).sum(-1, keepdim=True) + eps).sqrt()
    ha, hb = a - v0, b - v0
    ha = ha - (ha * e).sum(-1, keepdim=True) * e
    hb = hb - (hb * e).sum(-1, keepdim=True) * e
    cos = (ha * hb).sum(-1) / ((ha.pow(2).sum(-1) * hb.pow(2).sum(-1)) + eps).sqrt()
    return (1 + cos).pow(2).sum(1).mean()


def recon_loss(pred_sil: torch.Tensor, target_sil: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor,
               laplacian_weight: float = 5e-3, flatten_weight: float = 5e-4,
               scale: float = 1.0) -> dict[str, torch.Tensor]:
    """L_recon = L_s + mu L_g (Eq. 4.2): the silhouette IoU loss plus the weighted Laplacian and
    flatten losses (SoftRas's weights 5e-3, 5e-4). The vertices are divided by ``scale`` for the
    Laplacian loss (:meth:`ToolSynth.recon_loss` passes 2 x extent, SoftRas's unit cube side)."""
    silhouette = softras.iou_loss(pred_sil, target_sil)  # L_s
    laplacian = laplacian_loss(vertices / scale, faces)
    flatten = flatten_loss(vertices, faces)
    geometry = laplacian_weight * laplacian + flatten_weight * flatten  # mu L_g
    return {"silhouette": silhouette, "laplacian": laplacian, "flatten": flatten, "geometry": geometry,
            "total": silhouette + geometry}


# -- the task side: phi and the classifier ff (Appendix 4.B) -------------------------------------
class TaskEncoder(nn.Module):
    """phi: (B, 3, S, S) task image in [0, 1] -> z_G (B, z_task)."""

    def __init__(self, image_size: int = 64, z_task: int = 256, width: float = 1.0):
        super().__init__()
        layers: list[nn.Module] = []
        channels, side = 3, image_size
        for filters in TASK_FILTERS:
            out = _channels(filters, width)
            layers += [nn.Conv2d(channels, out, 5, stride=1, padding=2), nn.ELU(inplace=True),
                       nn.Conv2d(out, out, 5, stride=2, padding=2), nn.ELU(inplace=True)]
            channels, side = out, (side + 1) // 2
        self.side = side
        layers += [nn.Conv2d(channels, z_task, side, stride=1, padding=0), nn.ELU(inplace=True)]
        self.convs = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.convs(x.contiguous(memory_format=torch.channels_last)).flatten(1)


class Classifier(nn.Module):
    """ff: h_cat = [z_G, z_T] -> 2 logits (fail, success)."""

    def __init__(self, z_task: int = 256, z_tool: int = 512, hidden: tuple[int, int] = (1024, 512)):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(z_task + z_tool, hidden[0]), nn.ELU(inplace=True),
                                 nn.Linear(hidden[0], hidden[1]), nn.ELU(inplace=True), nn.Linear(hidden[1], 2))

    def forward(self, z_task: torch.Tensor, z_tool: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([z_task, z_tool], dim=1))  # h_cat


def success_logit(logits: torch.Tensor) -> torch.Tensor:
    """log p(success) / p(fail): p(success) = softmax(logits)[:, 1] = sigmoid(this)."""
    return logits[:, 1] - logits[:, 0]


def p_success(logits: torch.Tensor) -> torch.Tensor:
    return torch.softmax(logits, dim=1)[:, 1]


def jitter(z_tool: torch.Tensor, scale: float) -> torch.Tensor:
    """z_T plus Gaussian noise of ``scale`` times the batch's per-coordinate spread (detached), the
    classifier's input in training when ``train.latent_noise`` > 0. A classifier that must agree on
    a neighbourhood of each latent is smooth in z_T, and its gradient, which imagination follows,
    points where the other class's latents lie rather than along small moves that fool it
    (randomised smoothing; Kaur et al. 2019, "Are perceptually-aligned gradients a general property
    of robust classifiers?"). The spread is measured per batch, so the encoder cannot outgrow the
    noise by scaling its latents up."""
    if scale <= 0 or len(z_tool) < 2:
        return z_tool
    spread = z_tool.detach().std(dim=0, keepdim=True)
    return z_tool + scale * spread * torch.randn_like(z_tool)


def task_loss(logits: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """L_task (Eq. 4.3): the binary cross-entropy of p(success) against rho in {0, 1}, meaned."""
    return F.cross_entropy(logits, rho.long())


# -- inputs ---------------------------------------------------------------------------------------
def _batch(images, channels: bool) -> torch.Tensor:
    x = torch.as_tensor(np.asarray(images) if not torch.is_tensor(images) else images)
    return x[None] if x.dim() == (3 if channels else 2) else x


def tool_input(rgb_uint8, sil_uint8) -> torch.Tensor:
    """Tool images (B, S, S, 3) uint8 and silhouettes (B, S, S), 0/1 (or 0/255) -> (B, 4, S, S) in [0, 1]."""
    rgb, sil = _batch(rgb_uint8, True), _batch(sil_uint8, False)
    rgb = rgb.permute(0, 3, 1, 2).float() / 255.0
    return torch.cat([rgb, (sil > 0).float()[:, None]], dim=1)


def task_input(task_uint8) -> torch.Tensor:
    """Task images (B, S, S, 3) uint8 -> (B, 3, S, S) in [0, 1]."""
    return _batch(task_uint8, True).permute(0, 3, 1, 2).float() / 255.0


class ToolSynth(nn.Module):
    """psi, psi', phi and ff of Fig. 4.3; ``ToolSynth(**m.kwargs)`` rebuilds ``m`` (checkpoints)."""

    def __init__(self, image_size: int = 64, task_size: int = 64, z_tool: int = 512, z_task: int = 256,
                 width: float = 1.0, task_width: float = 1.0, subdivisions: int = 2, extent: float = 0.3,
                 norm: str = "batch", template_scale: tuple[float, float, float] = FLAT_TEMPLATE,
                 hidden: int = 1024, decoder_hidden: tuple[int, int] = (1024, 2048),
                 classifier_hidden: tuple[int, int] = (1024, 512), deform: str = "octant", latent: str = "linear"):
        super().__init__()
        self.kwargs = dict(image_size=image_size, task_size=task_size, z_tool=z_tool, z_task=z_task, width=width,
                           task_width=task_width, subdivisions=subdivisions, extent=extent, norm=norm,
                           template_scale=tuple(template_scale), hidden=hidden,
                           decoder_hidden=tuple(decoder_hidden), classifier_hidden=tuple(classifier_hidden),
                           deform=deform, latent=latent)
        self.extent = extent
        self.encoder = ToolEncoder(image_size, z_tool, width, norm, hidden, latent)  # psi
        self.decoder = MeshDecoder(z_tool, subdivisions, extent, tuple(template_scale), tuple(decoder_hidden),
                                   deform=deform)  # psi'
        self.task_encoder = TaskEncoder(task_size, z_task, task_width)  # phi
        self.classifier = Classifier(z_task, z_tool, tuple(classifier_hidden))  # ff

    @property
    def faces(self) -> torch.Tensor:
        return self.decoder.faces

    def encode_tool(self, rgb: torch.Tensor, sil: torch.Tensor | None = None) -> torch.Tensor:
        """z_T = psi(I_T, I_S) (Eq. 4.1) of uint8 images (B, S, S, 3) and silhouettes (B, S, S), or
        of float channels (B, 3, S, S) and (B, [1,] S, S), or of :func:`tool_input`'s (B, 4, S, S)."""
        if rgb.dtype == torch.uint8:
            x = tool_input(rgb, sil)
        elif sil is None:
            x = rgb
        else:
            x = torch.cat([rgb, (sil if sil.dim() == 4 else sil[:, None]).to(rgb.dtype)], dim=1)
        return self.encoder(x)

    def decode(self, z_tool: torch.Tensor) -> torch.Tensor:
        """psi'(z_T): vertices (B, V, 3) in metres; the triangles are :attr:`faces`."""
        return self.decoder(z_tool)

    def encode_task(self, task: torch.Tensor) -> torch.Tensor:
        """z_G = phi(I_G) of uint8 (B, S, S, 3) or float (B, 3, S, S) task images."""
        return self.task_encoder(task_input(task) if task.dtype == torch.uint8 else task)

    def classify(self, z_task: torch.Tensor, z_tool: torch.Tensor) -> torch.Tensor:
        """ff(h_cat): logits (B, 2) over (fail, success)."""
        return self.classifier(z_task, z_tool)

    def silhouettes(self, vertices: torch.Tensor, cams: softras.CameraTensors, index: torch.Tensor,
                    sigma: float = 1.0) -> torch.Tensor:
        """The soft silhouettes (B, H, W) of meshes ``vertices`` seen by cameras ``cams[index]``."""
        return softras.soft_silhouette(softras.project(vertices, cams, index), self.faces, cams.height, cams.width,
                                       sigma)

    def recon_loss(self, pred_sil: torch.Tensor, target_sil: torch.Tensor, vertices: torch.Tensor,
                   laplacian_weight: float = 5e-3, flatten_weight: float = 5e-4) -> dict[str, torch.Tensor]:
        """Eq. 4.2 on this model's mesh, the Laplacian measured in SoftRas's unit cube (side 2 x extent)."""
        return recon_loss(pred_sil, target_sil, vertices, self.faces, laplacian_weight, flatten_weight,
                          scale=2 * self.extent)

    def forward(self, tool: torch.Tensor, task: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Tool input (B, 4, S, S) and optional task images (B, 3, S, S) -> z_tool, vertices and,
        with a task, z_task and logits (B, 2)."""
        z_tool = self.encode_tool(tool)
        out = {"z_tool": z_tool, "vertices": self.decode(z_tool)}
        if task is not None:
            out["z_task"] = self.encode_task(task)
            out["logits"] = self.classify(out["z_task"], z_tool)
        return out


def _benchmark(batch: int = 32, size: int = 64, width: float = 0.5, steps: int = 5) -> None:
    """One training step of Eq. 4.4 (python -m physint_plugins.toolsynth.model): encode view i,
    decode, render in view j, L_recon + L_task, backward, Adam; random images, 12 ring cameras."""
    import time

    from physint_backends import Camera

    torch.manual_seed(0)
    el = math.radians(30)
    cams = softras.camera_tensors([Camera(f"view{k}", pos=(0.9 * math.cos(el) * math.cos(a), 0.9 * math.cos(el) *
                                                           math.sin(a), 0.9 * math.sin(el)), fovy=40.0, width=size,
                                          height=size) for k, a in enumerate(np.arange(12) * math.pi / 6)])
    m = ToolSynth(image_size=size, task_size=size, width=width, task_width=width)
    opt = torch.optim.Adam(m.parameters(), lr=3e-4)
    tool, task = torch.rand(batch, 4, size, size), torch.rand(batch, 3, size, size)
    target, rho, view_j = (torch.rand(batch, size, size) > 0.8).float(), torch.randint(0, 2, (batch,)), \
        torch.randint(0, 12, (batch,))
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        out = m(tool, task)
        sil = m.silhouettes(out["vertices"], cams, view_j, sigma=1.0)
        loss = m.recon_loss(sil, target, out["vertices"])["total"] + task_loss(out["logits"], rho)  # Eq. 4.4
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads: ToolSynth {size} px, width {width}, "
          f"batch {batch}: {1e3 * min(times):.0f} ms per step (best of {steps}; median {1e3 * np.median(times):.0f})")


if __name__ == "__main__":
    _benchmark()
