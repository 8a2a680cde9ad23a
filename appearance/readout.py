"""The DAM's output layer solved in closed form, its hidden layers kept (a *readout solve*).

A DAM is ``softplus(W h(x))``: hidden layers h, then one linear output layer W (3 x F, F the last
hidden width, plus a bias column when the architecture has biases). With h fixed, the fit's data
cost, weighted L1 of radiance in units of the model's radiance scale,

    C(W) = sum_i w_i |y_i - softplus(W h_i)| / sum_i w_i,

is a problem in 3 F unknowns that separates by colour channel. :func:`solve_output_layer` lowers
it by iteratively reweighted Gauss-Newton (each iteration one F x F linear solve per channel,
Levenberg-damped, with a halving line search that only accepts a lower cost), which takes
milliseconds where gradient descent on all the weights takes seconds.

``damcap predict`` uses it after the forward pass (``PredictOptions.readout_iterations``): the
predictor's hidden layers act as a basis of appearance, and the capture's own train pixels set
their mix. It is not iterative training of the network: the hidden layers (3264 of the paper's
3360 weights) stay as predicted. Pure: tensors in, tensors out.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, encode_inputs, hidden_activation, split_weights
from damcap.appearance.fit import weighted_quantile_cost
from damcap.appearance.pixels import PixelSamples

#: IRLS floor of |residual| (radiance in units of the model's scale): an L1 weight 1/|r| is at most 1000
IRLS_FLOOR = 1e-3
#: Levenberg damping, relative to the mean diagonal of each channel's normal matrix
DAMPING = 1e-3
#: line-search halvings before an iteration gives up (its step would be under 1/64)
HALVINGS = 7


def last_hidden(weights_flat: torch.Tensor, arch: DamArchitecture, inputs: torch.Tensor) -> torch.Tensor:
    """The features the output layer reads.

    Args:
        weights_flat: (P,) flat weights, or (B, P) for a batch of DAMs.
        arch: the architecture.
        inputs: (N, C) encoded inputs (:func:`.dam.encode_inputs`), or (B, N, C).

    Returns:
        (N, F) or (B, N, F): the last hidden layer's activations, with a column of ones appended
        when the architecture has biases (F = width, or width + 1), in weights_flat's dtype.
    """
    single = weights_flat.dim() == 1
    layers = split_weights(weights_flat[None] if single else weights_flat, arch)
    h = (inputs[None] if single else inputs).to(weights_flat.dtype)
    for w, b in layers[:-1]:
        h = torch.bmm(h, w.transpose(1, 2))
        h = hidden_activation(h if b is None else h + b[:, None, :], arch.activation)
    if arch.bias:
        h = torch.cat([h, torch.ones_like(h[..., :1])], -1)
    return h[0] if single else h


def output_layer(weights_flat: torch.Tensor, arch: DamArchitecture) -> torch.Tensor:
    """(3, F), or (B, 3, F) for (B, P) weights: the output layer's matrix, with its bias as the
    last column when the architecture has biases (the layout of :func:`last_hidden` 's features)."""
    single = weights_flat.dim() == 1
    w, b = split_weights(weights_flat[None] if single else weights_flat, arch)[-1]
    out = w if b is None else torch.cat([w, b[..., None]], -1)
    return out[0] if single else out


def with_output_layer(weights_flat: torch.Tensor, arch: DamArchitecture, w_out: torch.Tensor) -> torch.Tensor:
    """(..., P) the flat weights with the output layer (and bias) replaced by ``w_out`` (..., 3, F),
    which :func:`output_layer` lays out: a new tensor (differentiable in both; the input is not
    modified). The flat layout stores the output layer's matrix, then its bias, last."""
    o, i = arch.layer_shapes[-1]
    n = o * i + (o if arch.bias else 0)
    w_out = w_out.to(weights_flat.dtype)
    tail = w_out[..., :i].flatten(-2)
    if arch.bias:
        tail = torch.cat([tail, w_out[..., i]], -1)
    return torch.cat([weights_flat[..., :-n], tail], -1)


def l1_cost(h: torch.Tensor, w_out: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> float:
    """The fit's data cost (:func:`.fit.weighted_quantile_cost` at 0.5: weighted mean over samples
    of the channel-mean L1) of softplus(h W^T) against the target: (N, F), (3, F), (N, 3), (N,)."""
    return float(weighted_quantile_cost(F.softplus(h @ w_out.T), target, weight))


def irls_step(h: torch.Tensor, w_out: torch.Tensor, target: torch.Tensor, weight: torch.Tensor,
              damping: float = DAMPING, floor: float = IRLS_FLOOR) -> torch.Tensor:
    """One reweighted Gauss-Newton step of the output layer under the L1 cost.

    Per channel c: linearise softplus at z = h W_c (Jacobian sigmoid(z) h), weight each sample
    w_i / max(|r_i|, floor) (L1 as reweighted least squares; the weights are constants of the
    step, not differentiated), and solve the F x F normal equations with Levenberg damping
    ``damping`` x their mean diagonal. Leading batch dimensions (...) are allowed and independent.

    Args:
        h: (..., N, F) features; w_out: (..., 3, F) current output layer; target: (..., N, 3);
            weight: (..., N) (0 = the sample does not count).

    Returns:
        (..., 3, F) the Gauss-Newton point (the full step; :func:`solve_output_layer` searches along it).
    """
    z = h @ w_out.transpose(-1, -2)  # (..., N, 3)
    resid = target - F.softplus(z)
    irls = (weight[..., None] / resid.abs().clamp_min(floor)).detach()
    scale = torch.sigmoid(z)  # d softplus / dz
    normal = torch.einsum("...nc,...nf,...ng->...cfg", scale * scale * irls, h, h)
    diag = normal.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-6)  # (..., 3); the floor: dead features
    normal = normal + damping * diag[..., None, None] * torch.eye(h.shape[-1], dtype=h.dtype, device=h.device)
    rhs = torch.einsum("...nc,...nf->...cf", scale * irls * resid, h)
    return w_out + torch.linalg.solve(normal, rhs[..., None])[..., 0]


def solved_weights(weights_flat: torch.Tensor, arch: DamArchitecture, inputs: torch.Tensor, target: torch.Tensor,
                   weight: torch.Tensor, iterations: int, damping: float = DAMPING) -> torch.Tensor:
    """A batch of DAMs with their output layers solved: ``iterations`` full :func:`irls_step` s,
    no line search, differentiable (training a predictor through the solve, as ``train-hyper
    --readout-iterations`` does).

    Args:
        weights_flat: (B, P); inputs: (B, N, C) encoded; target: (B, N, 3) radiance in units of
            each DAM's scale; weight: (B, N) (0 = not in the solve).
        iterations: steps (0 = the weights as they are).

    Returns:
        (B, P) weights, the hidden layers' entries those of ``weights_flat``.
    """
    if iterations <= 0:
        return weights_flat
    h = last_hidden(weights_flat, arch, inputs)
    w_out = output_layer(weights_flat, arch)
    for _ in range(iterations):
        w_out = irls_step(h, w_out, target.to(h.dtype), weight.to(h.dtype), damping)
    return with_output_layer(weights_flat, arch, w_out)


@dataclass(frozen=True)
class ReadoutResult:
    """What :func:`solve_output_layer` did."""

    model: DeepAppearanceMap
    """the DAM with the solved output layer (the input model when no iteration lowered the cost)"""
    l1_before: float
    """the cost on the solve's samples before"""
    l1_after: float
    """and after (never higher)"""
    iterations: int
    """iterations that lowered the cost"""


@torch.no_grad()
def solve_output_layer(model: DeepAppearanceMap, samples: PixelSamples, iterations: int, max_samples: int,
                       seed: int = 0) -> ReadoutResult:
    """Lower the fit's data cost by re-solving the DAM's output layer on the given pixels.

    Each iteration takes :func:`irls_step`, then halves the step (at most :data:`HALVINGS` times)
    until the cost falls; an iteration that finds no lower cost ends the solve. Computed in
    float64.

    Args:
        model: a plain DAM (no spatial albedo or normal field; not modified); its radiance scale
            and hidden layers are kept.
        samples: covered pixels with known radiance (for ``damcap predict``: all train views').
        iterations: most iterations (0 = the model as it is).
        max_samples: a seeded random subset of at most this many samples is used (``damcap
            predict``: ``PredictOptions.readout_samples``).
        seed: the subset's seed.
    """
    if model.has_surface_factors:
        raise ValueError("the readout solve takes a plain DAM; this one has a spatial albedo or a normal field")
    arch = model.arch
    flat = model.get_flat_weights().detach().double()
    if iterations <= 0 or len(samples) == 0:
        return ReadoutResult(model, float("nan"), float("nan"), 0)
    idx = torch.randperm(len(samples), generator=torch.Generator().manual_seed(seed))[:max_samples]
    x = encode_inputs(samples.view_dir_world[idx], samples.normal_world[idx], arch.encoding).double()
    y = samples.radiance_lin[idx].double() / model.radiance_scale
    wt = samples.weight[idx].double()
    h = last_hidden(flat, arch, x)
    w_out = output_layer(flat, arch)
    before = cost = l1_cost(h, w_out, y, wt)
    done = 0
    for _ in range(iterations):
        full = irls_step(h, w_out, y, wt)
        t, accepted = 1.0, False
        for _ in range(HALVINGS):
            cand = w_out + t * (full - w_out)
            c = l1_cost(h, cand, y, wt)
            if c < cost and torch.isfinite(cand).all():
                w_out, cost, accepted = cand, c, True
                break
            t /= 2
        if not accepted:
            break
        done += 1
    if done == 0:
        return ReadoutResult(model, before, before, 0)
    out = DeepAppearanceMap(arch, model.radiance_scale, with_output_layer(flat, arch, w_out).float())
    return ReadoutResult(out, before, cost, done)
