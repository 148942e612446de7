"""The exported map as a standard 3D-GS renderer draws it: view-independent Gaussians fitted to
the training views.

A SEGS map decodes its Gaussians per view (Scaffold-GS: opacity, shape and colour depend on the
direction to the camera, and only the anchors inside the view's frustum are decoded). A PLY holds
one fixed set: the decoding from one view (the first keyframe's direction and appearance), drawn
from every other view with the anchors that view would have culled and the colours and
opacities of a direction it was not decoded for. `refine_cloud` starts from that set and fits
its Gaussians (positions, rotations, scales, opacities, colours) to the training images through
the rasterizer at full size with 3D-GS's 0.3 px^2 filter, the way a standard viewer draws them
(docs/decisions/036-exported-map-fitted-to-the-views.md). Nothing of the map itself changes.

The learning rates are the 3D-GS reference's for positions (times the scene extent), rotations,
scales and opacities; colours are fitted as logits, at 3e-2 (23.48 dB on the test views against
23.31 at 1e-2 after 500 steps on a map of the default schedule; the decision's page).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F

from segs.modules import losses
from segs.modules.contract import MIN_OPACITY, GaussianCloud, TrainingView

LR_MEANS, LR_QUATS, LR_LOG_SCALES, LR_OPACITY, LR_COLOR = 1.6e-4, 1e-3, 5e-3, 5e-2, 3e-2
LAMBDA_DSSIM = 0.2  # 3D-GS's photometric loss

# (Gaussians as rasterize() takes them: means [N,3], unit quats [N,4], scales [N,3], opacities [N],
# colours [N,3]; a training view) -> the rendered image [H,W,3]
Render = Callable[[tuple[torch.Tensor, ...], TrainingView], torch.Tensor]


def refine_cloud(cloud: GaussianCloud, views: Sequence[TrainingView], steps: int, render: Render, scene_extent: float,
                 device: torch.device | str = "cpu", seed: int = 0,
                 progress: Callable[[int], None] | None = None) -> GaussianCloud:  # fmt: skip
    """`cloud` fitted for `steps` steps (one training view each, drawn with a seeded generator)
    to the views' images by (1 - 0.2) L1 + 0.2 (1 - SSIM), on `device`; Gaussians whose opacity
    ends below 1/255 are dropped. render draws the Gaussians at a view (full size, 0.3 px^2);
    scene_extent (m) scales the positions' learning rate. progress(step) is called after every
    step. Returns a new cloud on the CPU (float32); `cloud` is unchanged."""
    if steps <= 0 or not views or len(cloud) == 0:
        return cloud
    params = {
        "means": cloud.means.to(device).clone(),
        "quats": cloud.quats.to(device).clone(),
        "log_scales": cloud.scales.to(device).clamp_min(1e-8).log(),
        "opacities": torch.logit(cloud.opacities.to(device), eps=1e-4),
        "colors": torch.logit(cloud.colors.to(device), eps=1e-4),
    }
    for p in params.values():
        p.requires_grad_(True)
    lrs = {"means": LR_MEANS * scene_extent, "quats": LR_QUATS, "log_scales": LR_LOG_SCALES, "opacities": LR_OPACITY, "colors": LR_COLOR}
    optimizer = torch.optim.Adam([{"params": [params[k]], "lr": lr} for k, lr in lrs.items()], eps=1e-15)
    order = torch.Generator().manual_seed(seed)
    with torch.enable_grad():
        for step in range(steps):
            view = views[int(torch.randint(len(views), (1,), generator=order))]
            image = render(_gaussians(params), view)  # the target: converted from uint8 here, none kept
            loss = losses.photometric(image, view.rgb().to(device), LAMBDA_DSSIM)["photometric"]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            if progress is not None:
                progress(step + 1)
    with torch.no_grad():
        means, quats, scales, opacities, colors = (t.detach().to("cpu", torch.float32) for t in _gaussians(params))
    keep = opacities >= MIN_OPACITY
    return GaussianCloud(means[keep], quats[keep], scales[keep], opacities[keep], colors[keep])


def _gaussians(params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """The fitted parameters as rasterize() takes them (means, unit quats, scales, opacities, colours)."""
    return (params["means"], F.normalize(params["quats"], dim=-1), params["log_scales"].exp(),
            torch.sigmoid(params["opacities"]), torch.sigmoid(params["colors"]))  # fmt: skip
