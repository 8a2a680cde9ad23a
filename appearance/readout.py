"""The DAM's output layer solved in closed form, its hidden layers kept (a *readout solve*), and
its first and output layers solved together (a *joint solve*).

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
3360 weights) stay as predicted.

The output layer can only mix the features it is given: where a predictor blurred a DAM's kinks
(in a bias-free leaky-ReLU DAM, the first layer's units switch on great circles of the normal and
mirror directions: a shadow terminator N . L = 0, the edge of a highlight), no mix makes them
sharp. :func:`solve_first_and_output_layers` also moves the first layer (192 weights in the
paper's DAM), by Levenberg-Marquardt on the same reweighted cost plus a prior pull toward the
given weights, the middle layers (3072 weights) as predicted. Its Jacobian needs one backward
pass per colour channel (:func:`joint_jacobian`), its normal matrix is (Q + 3 F) square
(:func:`joint_step`; 288 for the paper's DAM), so an iteration takes milliseconds too.

Pure: tensors in, tensors out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap, dam_forward, encode_inputs, hidden_activation, split_weights
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
    """What :func:`solve_output_layer` or :func:`solve_first_and_output_layers` did."""

    model: DeepAppearanceMap
    """the DAM with the solved layers (the input model when no iteration lowered the cost)"""
    l1_before: float
    """the data cost on the solve's samples before"""
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


# --------------------------------------------------------------------------------------------
# the first and output layers together
# --------------------------------------------------------------------------------------------

def first_layer_entries(arch: DamArchitecture) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each stored weight of the first layer sits in its (out, in) matrix, in the flat
    layout's order (:func:`.dam.split_weights`: row-major, a separable DAM's N block then its R
    block; biases not included).

    Returns:
        (n,) rows and (n,) columns, n = ``arch.layer_weight_counts[0]``.

    >>> rows, cols = first_layer_entries(DamArchitecture(width=4, depth=1, encoding="nr", separable=True))
    >>> rows.tolist(), cols.tolist()
    ([0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3], [0, 1, 2, 0, 1, 2, 3, 4, 5, 3, 4, 5])
    """
    (o, i), n = arch.layer_shapes[0], arch.layer_weight_counts[0]
    if n == o * i:
        r, c = torch.meshgrid(torch.arange(o), torch.arange(i), indexing="ij")
        return r.reshape(-1), c.reshape(-1)
    r, c = torch.meshgrid(torch.arange(o // 2), torch.arange(i // 2), indexing="ij")
    r, c = r.reshape(-1), c.reshape(-1)
    return torch.cat([r, r + o // 2]), torch.cat([c, c + i // 2])


def first_layer_size(arch: DamArchitecture) -> int:
    """Stored weights of the first layer: its matrix entries, plus its biases when it has them."""
    return arch.layer_weight_counts[0] + (arch.layer_shapes[0][0] if arch.bias else 0)


def joint_jacobian(weights_flat: torch.Tensor, arch: DamArchitecture, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The DAM's output before its softplus, and what the first and output layers do to it.

    Samples are independent given the weights, so one backward pass per colour channel of the
    summed output gives every sample's gradient at the first layer's pre-activations, G (the
    chain through the hidden layers, for any activation); the first layer's entry (j, k) then
    has derivative G_j x_k, its bias G_j, and the output layer's row c has h (the last hidden
    features, :func:`last_hidden`) for channel c and 0 for the others.

    Args:
        weights_flat: (P,) one DAM's flat weights (its dtype is the computation's).
        arch: its architecture.
        inputs: (N, C) encoded inputs.

    Returns:
        z: (N, 3) the output layer's values (radiance = softplus(z), in units of the model's scale).
        jac_first: (N, 3, Q) dz / d(first layer's stored weights, then its biases),
            Q = :func:`first_layer_size`.
        h: (N, F) the last hidden features (dz_c / d(output row c) = h).
    """
    layers = split_weights(weights_flat[None].detach(), arch)
    x = inputs.to(weights_flat.dtype)
    w0, b0 = layers[0]
    with torch.enable_grad():
        z0 = (x @ w0[0].T + (0 if b0 is None else b0[0])).requires_grad_(True)
        a = z0
        for w, b in layers[1:]:
            a = hidden_activation(a, arch.activation) @ w[0].T + (0 if b is None else b[0])
        grads = [torch.autograd.grad(a[:, c].sum(), z0, retain_graph=c < 2)[0] for c in range(3)]
    g = torch.stack(grads, 1)  # (N, 3, out0)
    rows, cols = first_layer_entries(arch)
    jac = g[:, :, rows] * x[:, None, cols]
    if arch.bias:
        jac = torch.cat([jac, g], -1)
    return a.detach(), jac, last_hidden(weights_flat.detach(), arch, inputs)


def with_first_layer(weights_flat: torch.Tensor, arch: DamArchitecture, first: torch.Tensor) -> torch.Tensor:
    """(P,) the flat weights with the first layer's stored weights (then its biases) replaced by
    ``first`` (Q,): a new tensor."""
    return torch.cat([first.to(weights_flat.dtype), weights_flat[first_layer_size(arch):]])


def joint_step(jac_first: torch.Tensor, h: torch.Tensor, z: torch.Tensor, target: torch.Tensor, weight: torch.Tensor,
               damping: float, prior: float = 0.0, offset: torch.Tensor | None = None, floor: float = IRLS_FLOOR) -> torch.Tensor:
    """One reweighted, Levenberg-damped Gauss-Newton step of the first and output layers together
    under the L1 cost (as :func:`irls_step`, with the first layer's columns added).

    The unknowns are the first layer's Q weights then the output layer's 3 x F, row by row; the
    residual of sample n, channel c is y - softplus(z), linearised with Jacobian sigmoid(z) times
    [jac_first, h in block c], weighted w_n / max(|r|, floor). With ``prior`` mu > 0 the cost is
    C + mu |theta - theta_0|^2 (``offset`` = theta - theta_0): its curvature 2 mu and gradient
    2 mu offset join the normal equations, in their units (times 3 sum_n w_n, since C is the
    weighted mean over samples of the channel mean). The damping is ``damping`` times the normal
    matrix's mean diagonal. The normal matrix is built in the inputs' dtype and solved in float64.

    Args:
        jac_first: (N, 3, Q); h: (N, F); z: (N, 3); target: (N, 3), in units of the model's
            radiance scale; weight: (N,).
        damping: Levenberg damping, relative.
        prior: mu, in units of the cost per squared weight.
        offset: (Q + 3 F,) theta - theta_0 (needed when prior > 0).

    Returns:
        (Q + 3 F,) the step, in the inputs' dtype.
    """
    n, _, q = jac_first.shape
    f = h.shape[1]
    resid = target - F.softplus(z)
    s = torch.sigmoid(z)
    irls = (weight[:, None] / resid.abs().clamp_min(floor)).detach()
    jf = jac_first * s[..., None]  # (N, 3, Q)
    hs = h[:, None, :] * s[..., None]  # (N, 3, F): channel c's output-row derivative
    jw = jf * irls[..., None]
    size = q + 3 * f
    normal = torch.zeros(size, size, dtype=h.dtype, device=h.device)
    normal[:q, :q] = jw.reshape(-1, q).T @ jf.reshape(-1, q)
    rhs = torch.empty(size, dtype=h.dtype, device=h.device)
    rhs[:q] = jw.reshape(-1, q).T @ resid.reshape(-1)
    for c in range(3):
        o = slice(q + c * f, q + (c + 1) * f)
        hw = hs[:, c] * irls[:, c, None]
        cross = jw[:, c].T @ hs[:, c]  # (Q, F)
        normal[:q, o], normal[o, :q] = cross, cross.T
        normal[o, o] = hw.T @ hs[:, c]
        rhs[o] = hw.T @ resid[:, c]
    normal, rhs = normal.double(), rhs.double()
    eye = torch.eye(size, dtype=normal.dtype, device=h.device)
    if prior > 0 and offset is not None:  # the cost's prior term mu |theta - theta_0|^2, in the normal matrix's units
        scale = 6 * float(weight.sum())
        normal = normal + prior * scale * eye
        rhs = rhs - prior * scale * offset.double()
    diag = normal.diagonal().mean().clamp_min(1e-12)
    step = torch.linalg.solve(normal + damping * diag * eye, rhs)
    return step.to(h.dtype)


@torch.no_grad()
def solve_first_and_output_layers(model: DeepAppearanceMap, samples: PixelSamples, iterations: int, max_samples: int,
                                  prior: float = 0.0, seed: int = 0, damping: float = DAMPING,
                                  dtype: torch.dtype = torch.float32) -> ReadoutResult:
    """Lower the fit's data cost by solving the DAM's first and output layers together, the
    middle hidden layers kept (:func:`solve_output_layer` solves the output layer alone).

    The first layer places the kinks of the DAM (for a bias-free leaky-ReLU DAM, great circles
    of normal and mirror directions: a terminator N . L = 0, the edge of a highlight), the
    output layer mixes the features; moving both lets a predicted DAM sharpen what its
    predictor blurred. The cost is the fit's L1 plus ``prior`` times the squared distance of the
    solved weights from the model's: the given DAM is the prior, and a capture that the DAM
    cannot explain (a point light's fall-off, cast shadows) pulls the kinks less far.
    Levenberg-Marquardt on :func:`joint_step`: an iteration whose step does not lower the cost
    is retried with 4x the damping (at most :data:`HALVINGS` times; then the solve ends), one
    that does lowers the damping 3x for the next.

    Args:
        model: a plain DAM (not modified); its radiance scale and middle layers are kept.
        samples: covered pixels with known radiance.
        iterations: most iterations (0 = the model as it is).
        max_samples: a seeded random subset of at most this many samples is used.
        prior: mu >= 0, in units of the cost per squared weight.
        seed: the subset's seed.
        damping: the first iteration's damping, relative to the normal matrix's mean diagonal.
        dtype: of the Jacobian and the normal matrix (float32 by default: half of float64's
            time on a 2-core CPU, the same novel-view DSSIM to 4 decimals on two issue-28
            captures); the linear solves are float64.

    Returns:
        the solved DAM, with the data cost (L1, without the prior term) on the solve's samples
        before and after.
    """
    if model.has_surface_factors:
        raise ValueError("the readout solve takes a plain DAM; this one has a spatial albedo or a normal field")
    arch = model.arch
    flat = model.get_flat_weights().detach().to(dtype)
    if iterations <= 0 or len(samples) == 0:
        return ReadoutResult(model, float("nan"), float("nan"), 0)
    idx = torch.randperm(len(samples), generator=torch.Generator().manual_seed(seed))[:max_samples]
    x = encode_inputs(samples.view_dir_world[idx], samples.normal_world[idx], arch.encoding).to(dtype)
    y = samples.radiance_lin[idx].to(dtype) / model.radiance_scale
    wt = samples.weight[idx].to(dtype)
    q = first_layer_size(arch)

    def unpack(theta: torch.Tensor) -> torch.Tensor:
        return with_output_layer(with_first_layer(flat, arch, theta[:q]), arch, theta[q:].reshape(3, -1))

    def cost_of(w: torch.Tensor) -> float:
        return float(weighted_quantile_cost(dam_forward(w, x, arch), y, wt))

    theta = theta_0 = torch.cat([flat[:q], output_layer(flat, arch).reshape(-1)])
    before = cost = cost_of(flat)
    lam, done = damping, 0
    for _ in range(iterations):
        z, jac, h = joint_jacobian(unpack(theta), arch, x)
        accepted = False
        for _ in range(HALVINGS):
            cand = theta + joint_step(jac, h, z, y, wt, lam, prior, theta - theta_0)
            c = cost_of(unpack(cand)) + prior * float(((cand - theta_0) ** 2).sum()) if torch.isfinite(cand).all() else math.inf
            if c < cost:
                theta, cost, accepted, lam = cand, c, True, lam / 3
                break
            lam *= 4
        if not accepted:
            break
        done += 1
    if done == 0:
        return ReadoutResult(model, before, before, 0)
    solved = unpack(theta)
    return ReadoutResult(DeepAppearanceMap(arch, model.radiance_scale, solved.float()), before, cost_of(solved), done)
