"""A prior for the fit (``damcap fit --prior predictor``): the shipped predictor's DAM, trusted
where the training views say least.

A fit minimises its data cost over the training pixels only; (view, normal) pairs that no
training view showed (another elevation, the far side of a highlight) get whatever the network
extrapolates to, and as the steps accumulate the extrapolation drifts. The predictor's DAM
(:func:`.hyper.predict.predict_views`) was learned from many objects seen from every side, so it
carries an answer for those pairs. The prior adds to the fit's cost the L1 distance between the
fitted and the predicted DAM on (view, normal) samples drawn once (:func:`prior_samples`): the
training pixels' normals, each with a view direction uniform on its hemisphere, each weighted by
how far it lies from every training pixel in the DAM's input encoding
(:func:`unconstrained_weight`): 0 on a training pixel, where the data decide, towards 1 far from
all of them, where the prior does.

Pure: tensors in, tensors out (the predictor is read by the caller).
"""

from __future__ import annotations

import torch

from damcap.appearance.dam import DeepAppearanceMap, Encoding, encode_inputs
from damcap.appearance.fit import PriorSamples
from damcap.appearance.pixels import PixelSamples

TRAIN_REFERENCE = 8192
"""training pixels (a seeded subset) each prior sample's distance is measured to"""


def hemisphere_view_dirs(normal_world: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """View directions uniform on the hemisphere around each normal.

    Args:
        normal_world: (M, 3) unit normals, world space.
        generator: seeds the directions.

    Returns:
        (M, 3) unit vectors v with v . n >= 0 (surface towards the camera, as
        :func:`.pixels.view_dir_world`).

    >>> n = torch.tensor([[0.0, 0.0, 1.0]] * 1000)
    >>> v = hemisphere_view_dirs(n, torch.Generator().manual_seed(0))
    >>> bool((v[:, 2] >= 0).all()), round(float(v[:, 2].mean()), 1)
    (True, 0.5)
    """
    v = torch.randn(normal_world.shape, generator=generator, dtype=normal_world.dtype)
    v = v / v.norm(dim=1, keepdim=True).clamp_min(1e-12)
    flip = (v * normal_world).sum(1, keepdim=True) < 0
    return torch.where(flip, -v, v)


def nearest_distance(x: torch.Tensor, reference: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """(M,) Euclidean distance from each row of ``x`` (M, C) to its nearest row of ``reference``
    (T, C), in chunks of ``chunk`` rows.

    >>> nearest_distance(torch.tensor([[0.0, 0.0], [3.0, 4.0]]), torch.tensor([[0.0, 0.0]])).tolist()
    [0.0, 5.0]
    """
    if reference.shape[0] == 0:
        return torch.full((x.shape[0],), float("inf"))
    return torch.cat([torch.cdist(x[s:s + chunk], reference).min(1).values for s in range(0, x.shape[0], chunk)])


def unconstrained_weight(distance: torch.Tensor, sigma: float) -> torch.Tensor:
    """How little the training pixels constrain a sample ``distance`` away from the nearest of
    them (in the DAM's input encoding): 1 - exp(-(d / sigma)^2), 0 on a training pixel, 0.63 at
    sigma, 1 far away.

    >>> [round(float(w), 2) for w in unconstrained_weight(torch.tensor([0.0, 0.25, 1.0]), 0.25)]
    [0.0, 0.63, 1.0]
    """
    return 1 - torch.exp(-(distance / sigma) ** 2)


@torch.no_grad()
def prior_samples(prior: DeepAppearanceMap, samples: PixelSamples, encoding: Encoding, radiance_scale: float, count: int,
                  sigma: float, seed: int = 0) -> PriorSamples:
    """The prior's answers where the fit needs them (module docstring).

    Args:
        prior: the prior DAM (any architecture; its own radiance scale).
        samples: the fit's training pixels (normals drawn from them; distances measured to them).
        encoding: the fit's DAM input encoding.
        radiance_scale: the fit's radiance scale (targets are divided by it, as the data's are).
        count: prior samples M.
        sigma: :func:`unconstrained_weight`'s distance.
        seed: seeds the normals, the view directions and the training subset.

    Returns:
        :class:`.fit.PriorSamples` of M samples (none when ``samples`` is empty).
    """
    gen = torch.Generator().manual_seed(seed)
    n = len(samples)
    if n == 0 or count == 0:
        none = torch.zeros(0, 3)
        return PriorSamples(encode_inputs(none, none, encoding), none, torch.zeros(0))
    normal = samples.normal_world[torch.randint(0, n, (count,), generator=gen)].float()
    view = hemisphere_view_dirs(normal, gen)
    target = prior(view, normal) / radiance_scale
    inputs = encode_inputs(view, normal, encoding)
    ref = torch.randperm(n, generator=gen)[:TRAIN_REFERENCE]
    train_inputs = encode_inputs(samples.view_dir_world[ref].float(), samples.normal_world[ref].float(), encoding)
    weight = unconstrained_weight(nearest_distance(inputs, train_inputs), sigma)
    return PriorSamples(inputs.float(), target.float(), weight.float())
