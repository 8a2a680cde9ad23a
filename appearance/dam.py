"""The deep appearance map: a tiny MLP from (view direction, normal) in world space to RGB.

Maximov et al. 2019, Sec. 3: the paper's network has 3360 weights (4 hidden layers of 32, no
biases) on the raw 6 inputs. The weights live in ONE flat parameter vector so that a
learning-to-learn network can produce them directly (:func:`dam_forward` takes a batch of
weight vectors).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Literal, get_args

import torch
import torch.nn.functional as F
from torch import nn

from damcap.common.errors import DamcapError
from damcap.common.numerics import reflect, safe_normalize
from damcap.common.validate import MAX_DAM_DEPTH, MAX_DAM_WIDTH, bounded_int, finite_in

if TYPE_CHECKING:
    from damcap.appearance.normal_field import NormalField
    from damcap.appearance.spatial import SpatialAlbedo

Encoding = Literal["vn", "nr", "vnr"]
Activation = Literal["leaky_relu", "relu", "softplus", "shifted_softplus", "tanh"]
ACTIVATIONS: tuple[str, ...] = get_args(Activation)
LN2 = math.log(2.0)
#: smallest positive normal float32
FLOAT32_TINY = 1.1754943508222875e-38

ENCODING_DIMS = {"vn": 6, "nr": 6, "vnr": 9}


@dataclass(frozen=True)
class DamArchitecture:
    """Shape of a deep appearance map."""

    width: int = 32
    """units per hidden layer"""
    depth: int = 4
    """hidden layers"""
    activation: Activation = "leaky_relu"
    """hidden non-linearity (see :func:`hidden_activation`); ``damcap fit``'s default is
    'shifted_softplus' (FitOptions), the predictor and the segmentation DAMs use this one"""
    encoding: Encoding = "nr"
    """network input: 'vn' = (V, N), the paper's raw 6 numbers; 'nr' = (N, R) with R the view
    mirrored about N (also 6 numbers, same information: V = 2 (N.R) N - R; specular lobes under
    distant light are functions of R); 'vnr' = all 9"""
    bias: bool = False
    """biases in every layer (the paper: none)"""
    separable: bool = False
    """encoding 'nr' only: the hidden units split into two equal halves, one seeing only N, the
    other only R (block-diagonal hidden layers; the output layer adds both), so the DAM is
    softplus(f(N) + g(R)): a diffuse-like term of the normal plus a specular-like term of the
    mirrored view. ``width`` counts both halves; the structural zeros are not stored"""

    def __post_init__(self) -> None:
        # bounded before anything (layer_shapes, the weight vector) is built from them; a whole
        # float (32.0) is kept as the int it stands for, so that slices and shapes take it
        object.__setattr__(self, "width", bounded_int(self.width, 1, MAX_DAM_WIDTH, "DAM width"))
        object.__setattr__(self, "depth", bounded_int(self.depth, 1, MAX_DAM_DEPTH, "DAM depth"))
        if not isinstance(self.bias, bool) or not isinstance(self.separable, bool):
            raise DamcapError(f"DAM bias and separable must be true or false, got bias={self.bias!r}, separable={self.separable!r}")
        if self.encoding not in ENCODING_DIMS:
            raise DamcapError(f"unknown DAM input encoding {self.encoding!r}; use one of {sorted(ENCODING_DIMS)}")
        if self.activation not in ACTIVATIONS:
            raise DamcapError(f"unknown activation {self.activation!r}; use one of {', '.join(ACTIVATIONS)}")
        if self.separable and (self.encoding != "nr" or self.width % 2):
            raise DamcapError(f"a separable DAM needs the encoding 'nr' and an even width, got encoding "
                              f"{self.encoding!r}, width {self.width}")

    @property
    def layer_shapes(self) -> list[tuple[int, int]]:
        """(out, in) of each linear layer, input to output."""
        dims = [ENCODING_DIMS[self.encoding]] + [self.width] * self.depth + [3]
        return [(dims[k + 1], dims[k]) for k in range(len(dims) - 1)]

    @property
    def layer_weight_counts(self) -> list[int]:
        """Stored matrix entries per linear layer: out x in, or half of that for a separable
        DAM's block-diagonal first and hidden layers (its output layer is full)."""
        last = len(self.layer_shapes) - 1
        return [o * i // 2 if self.separable and k < last else o * i for k, (o, i) in enumerate(self.layer_shapes)]

    @property
    def num_weights(self) -> int:
        """Length of the flat weight vector.

        >>> DamArchitecture(encoding="vn").num_weights
        3360
        >>> DamArchitecture(width=44, separable=True).num_weights
        3168
        """
        return sum(n + (o if self.bias else 0) for n, (o, _) in zip(self.layer_weight_counts, self.layer_shapes))

    def to_json(self) -> dict:
        return asdict(self)


def encode_inputs(view_dir_world: torch.Tensor, normal_world: torch.Tensor, encoding: Encoding) -> torch.Tensor:
    """The network input of a DAM.

    Args:
        view_dir_world: (..., 3) unit vectors from the surface toward the camera (any float dtype).
        normal_world: (..., 3) unit normals.
        encoding: see :class:`DamArchitecture`.

    Returns:
        (..., 6 or 9) float32 (inputs are renormalised: half-precision or interpolated normals
        do not change the result beyond rounding).
    """
    v = safe_normalize(view_dir_world.float())
    n = safe_normalize(normal_world.float())
    if encoding == "vn":
        return torch.cat([v, n], -1)
    r = reflect(v, n)
    if encoding == "nr":
        return torch.cat([n, r], -1)
    return torch.cat([v, n, r], -1)


def hidden_activation(x: torch.Tensor, name: Activation) -> torch.Tensor:
    """A hidden layer's non-linearity, elementwise.

    'shifted_softplus' is softplus(x) - ln 2: smooth like softplus, and 0 at 0 like ReLU. The
    shift matters without biases: plain softplus units are all positive, so a bias-free layer
    after them adds a large common offset to every input, and under a point light (more than
    half the pixels black, so the L1 optimum of that offset is black) fits can collapse to a
    black image in their first steps (measured: bench/synth.md).

    >>> hidden_activation(torch.tensor([0.0, 30.0]), "shifted_softplus")
    tensor([ 0.0000, 29.3069])
    """
    if name == "leaky_relu":
        return F.leaky_relu(x, 0.01)
    if name == "relu":
        return F.relu(x)
    if name == "softplus":
        return F.softplus(x)
    if name == "shifted_softplus":
        return F.softplus(x) - LN2
    return torch.tanh(x)


def split_weights(weights_flat: torch.Tensor, arch: DamArchitecture) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
    """Per-layer (B, out, in) matrices and (B, out) biases of a (B, P) flat weight batch.

    The flat layout is layer by layer: the matrix row-major (a separable DAM's N block, then its
    R block), then the biases. A separable DAM's block-diagonal matrices are assembled with
    their zeros from tensor ops only, so that torch.export traces them."""
    layers = []
    k = 0
    for (o, i), n in zip(arch.layer_shapes, arch.layer_weight_counts):
        if n < o * i:  # block-diagonal: the N block, then the R block, each (o/2, i/2) row-major
            w_n = weights_flat[:, k:k + n // 2].reshape(-1, o // 2, i // 2)
            w_r = weights_flat[:, k + n // 2:k + n].reshape(-1, o // 2, i // 2)
            zero = torch.zeros_like(w_n)
            w = torch.cat([torch.cat([w_n, zero], 2), torch.cat([zero, w_r], 2)], 1)
        else:
            w = weights_flat[:, k:k + n].reshape(-1, o, i)
        k += n
        b = None
        if arch.bias:
            b = weights_flat[:, k:k + o]
            k += o
        layers.append((w, b))
    return layers


def dam_forward(weights_flat: torch.Tensor, inputs: torch.Tensor, arch: DamArchitecture) -> torch.Tensor:
    """Evaluate a batch of DAMs.

    Args:
        weights_flat: (P,) or (B, P) flat weights (P = arch.num_weights).
        inputs: (N, C) or (B, N, C) encoded inputs (:func:`encode_inputs`).
        arch: the architecture.

    Returns:
        (N, 3) or (B, N, 3) radiance in units of the model's radiance scale, >= 0 and finite
        (softplus output).
    """
    single = weights_flat.dim() == 1
    if single:
        weights_flat, inputs = weights_flat[None], inputs[None]
    if weights_flat.shape[-1] != arch.num_weights:
        raise ValueError(f"expected {arch.num_weights} weights, got {weights_flat.shape[-1]}")
    x = inputs.to(weights_flat.dtype)
    layers = split_weights(weights_flat, arch)
    for k, (w, b) in enumerate(layers):
        if x.shape[0] == 1:  # one network: a plain matrix product (faster than bmm on CPU)
            x = torch.nn.functional.linear(x[0], w[0], None if b is None else b[0])[None]
        else:
            x = torch.bmm(x, w.transpose(1, 2))
            if b is not None:
                x = x + b[:, None, :]
        if k < len(layers) - 1:
            x = hidden_activation(x, arch.activation)
    if x.dtype in (torch.float16, torch.bfloat16):
        x = x.float()  # the output is radiance: never in a format that overflows at 65504
    out = F.softplus(x).clamp_max(torch.finfo(x.dtype).max)
    return out[0] if single else out


def rotated_world_weights(weights_flat: torch.Tensor, arch: DamArchitecture, rotation: torch.Tensor) -> torch.Tensor:
    """The weights of the DAM that reads rotated world vectors: f'(V, N) = f(R V, R N).

    Every input encoding is made of world vectors (V, N, R = reflect(V, N)), and reflection
    commutes with rotation, so rotating the world multiplies each 3-vector block of the input by
    R: only the first layer changes, each (unit, block) row w becoming w R. A predictor that works
    in a frame of its own (``R`` taking world vectors into it) returns its DAM to the world this way.

    Args:
        weights_flat: (P,) or (B, P) flat weights.
        arch: the architecture.
        rotation: (3, 3) or (B, 3, 3) rotation matrix R.

    Returns:
        weights of the same shape (a new tensor, differentiable in both inputs).

    >>> a = DamArchitecture(width=4, depth=1)
    >>> w = torch.randn(a.num_weights)
    >>> torch.equal(rotated_world_weights(w, a, torch.eye(3)), w)
    True
    """
    n0 = arch.layer_weight_counts[0]  # first layer's matrix: consecutive triples are (unit, block) rows
    first = weights_flat[..., :n0].reshape(*weights_flat.shape[:-1], n0 // 3, 3)
    rot = rotation.to(weights_flat.dtype)
    turned = (first @ rot).reshape(*weights_flat.shape[:-1], n0)
    return torch.cat([turned, weights_flat[..., n0:]], -1)


def init_weights(arch: DamArchitecture, generator: torch.Generator | None = None) -> torch.Tensor:
    """He-uniform initial flat weights (fan-in: the inputs a unit sees), (P,) float32; biases 0."""
    parts = []
    for n, (o, _) in zip(arch.layer_weight_counts, arch.layer_shapes):
        bound = math.sqrt(6.0 / (n // o))
        parts.append((torch.rand(n, generator=generator) * 2 - 1) * bound)
        if arch.bias:
            parts.append(torch.zeros(o))
    return torch.cat(parts)


#: float32 range: every hidden value and output of a DAM must stay inside it (renders, GLSL)
FLOAT32_MAX = float(torch.finfo(torch.float32).max)
#: matrix entries x inputs of the overflow probe (about 2 x this many multiply-adds)
PROBE_WORK = 1 << 26


def output_bound(weights_flat: torch.Tensor, arch: DamArchitecture) -> float:
    """An upper bound of |every hidden value| and of the normalised output over ALL unit inputs.

    Interval arithmetic in float64: inputs are components of unit vectors (|x| <= 1), each layer
    maps a bound b to |W| b + |bias|, the activations add at most ln 2 (tanh caps at 1).

    Args:
        weights_flat: (P,) flat weights.
        arch: the architecture.

    Returns:
        the bound (inf or NaN when it overflows float64).
    """
    layers = split_weights(weights_flat.detach()[None], arch)
    x = torch.ones(arch.layer_shapes[0][1], dtype=torch.float64)
    worst = 0.0
    for k, (w, b) in enumerate(layers):  # one layer at a time in float64 (memory: one matrix)
        x = w[0].double().abs() @ x + (0.0 if b is None else b[0].double().abs())
        top = float(x.max())
        if not math.isfinite(top):
            return top
        worst = max(worst, top)
        x = x.clamp_max(1.0) if arch.activation == "tanh" and k < len(layers) - 1 else x + LN2
    return max(worst, float(x.max()))


def _probe_inputs(n: int, encoding: Encoding) -> torch.Tensor:
    """(n, C) encoded inputs of n fixed (view, normal) pairs spread over the sphere (Fibonacci)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    pts = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)
    return encode_inputs(pts.roll(n // 3, 0), pts, encoding)


def overflow_problem(model: "DeepAppearanceMap") -> str | None:
    """Why the model's hidden values or radiance can leave float32 (inf, NaN), or None when they cannot.

    Finite weights are not enough: 3e38 is a finite float32 weight, and one layer of them
    overflows. The bound of :func:`output_bound` proves a model safe; a deep model can exceed
    that loose bound and still be fine, so it is then evaluated, layer by layer in float32, on
    fixed directions spread over the sphere.
    """
    w, arch, scale = model.weights_flat.detach().float(), model.arch, model.radiance_scale
    largest = float(w.abs().max()) if w.numel() else 0.0
    bound = output_bound(w, arch)
    if bound * scale <= FLOAT32_MAX:
        return None
    n = max(16, min(4096, PROBE_WORK // max(1, arch.num_weights)))
    x = _probe_inputs(n, arch.encoding)
    layers = split_weights(w[None], arch)
    for k, (mat, b) in enumerate(layers):
        x = F.linear(x, mat[0], None if b is None else b[0])
        if k < len(layers) - 1:
            x = hidden_activation(x, arch.activation)
        ok = bool(torch.isfinite(x).all()) and (k < len(layers) - 1 or bool((F.softplus(x) * scale < FLOAT32_MAX).all()))
        if not ok:
            return (f"the weights (largest |w| = {largest:.4g}) overflow float32: layer {k + 1} of "
                    f"{len(layers)} gives inf or NaN for some view and normal directions")
    return None


class DeepAppearanceMap(nn.Module):
    """A DAM: one flat weight vector plus its architecture and the radiance scale of its capture.

    ``forward(view_dir_world, normal_world)`` returns linear radiance in the capture's units.
    ``spatial`` (None, or a :class:`.spatial.SpatialAlbedo`) is the optional spatial factor that
    multiplies it per surface point; ``normal_field`` (None, or a :class:`.normal_field.NormalField`)
    the optional refinement of the surface's normals (relief the geometry lacks). Both belong to
    the capture's surface: ``forward`` is the DAM alone, renderers apply them where they know the
    surface point (:func:`.render.render_frame`).
    """

    def __init__(self, arch: DamArchitecture, radiance_scale: float = 1.0, weights_flat: torch.Tensor | None = None, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.arch = arch
        # float32: the scale multiplies float32 radiance; 1e39 is finite in float64 but renders inf
        scale = finite_in(radiance_scale, "float32", "radiance scale")
        if not scale >= FLOAT32_TINY:  # positive in float32 too (1e-50 would round to 0)
            raise DamcapError(f"radiance scale must be a positive finite number (>= {FLOAT32_TINY:.4g}), got {radiance_scale}")
        self.radiance_scale = scale
        w = init_weights(arch, generator) if weights_flat is None else weights_flat.detach().float().clone()
        if w.shape != (arch.num_weights,):
            raise DamcapError(f"weight vector has shape {tuple(w.shape)}, the architecture needs ({arch.num_weights},)")
        self.weights_flat = nn.Parameter(w)
        self.spatial: SpatialAlbedo | None = None
        self.normal_field: NormalField | None = None

    def with_spatial(self, spatial: "SpatialAlbedo | None") -> "DeepAppearanceMap":
        """A copy of this DAM (same weights, same normal field) carrying ``spatial`` as its spatial factor."""
        out = DeepAppearanceMap(self.arch, self.radiance_scale, self.get_flat_weights().cpu())
        out.spatial, out.normal_field = spatial, self.normal_field
        return out

    def with_normal_field(self, normal_field: "NormalField | None") -> "DeepAppearanceMap":
        """A copy of this DAM (same weights, same spatial factor) carrying ``normal_field``."""
        out = self.with_spatial(self.spatial)
        out.normal_field = normal_field
        return out

    def dam_alone(self) -> "DeepAppearanceMap":
        """A copy without the surface's factors (spatial factor, normal field)."""
        return self.with_spatial(None).with_normal_field(None)

    @property
    def has_surface_factors(self) -> bool:
        """Whether the model carries a spatial factor or a normal field (both tied to its capture's surface)."""
        return self.spatial is not None or self.normal_field is not None

    def forward_normalised(self, inputs: torch.Tensor) -> torch.Tensor:
        """(N, C) encoded inputs -> (N, 3) radiance / radiance_scale."""
        return dam_forward(self.weights_flat, inputs, self.arch)

    def forward(self, view_dir_world: torch.Tensor, normal_world: torch.Tensor) -> torch.Tensor:
        """(N, 3) view directions and normals -> (N, 3) linear radiance, >= 0."""
        return self.forward_normalised(encode_inputs(view_dir_world, normal_world, self.arch.encoding)) * self.radiance_scale

    def get_flat_weights(self) -> torch.Tensor:
        """(P,) copy of the weights."""
        return self.weights_flat.detach().clone()

    def set_flat_weights(self, weights_flat: torch.Tensor) -> None:
        """Replace the weights by a (P,) vector."""
        if weights_flat.shape != self.weights_flat.shape:
            raise DamcapError(f"weight vector has shape {tuple(weights_flat.shape)}, expected {tuple(self.weights_flat.shape)}")
        with torch.no_grad():
            self.weights_flat.copy_(weights_flat)
