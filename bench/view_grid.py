"""A picture of what DAMs do on a capture's novel views: one row per test view, the photo then each
model's rendering, titled with its DSSIM (``appearance.evaluate.score_view``), all tone-mapped
alike (divided by the photo's 99th percentile of covered radiance, then
``common.colour.preview_gamma``).

    .venv/bin/python -m bench.view_grid CAPTURE --model NAME=FILE.dam [--model ...] --rows 4 --out PNG

bench/hyper_ood.md's history shows three (``bench/predict_distant_light*.png``), with the commands
that made their models.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from damcap.appearance.dam_file import load_dam
    from damcap.appearance.evaluate import score_view
    from damcap.appearance.render import render_frame
    from damcap.appearance.views import load_views
    from damcap.common.atomic import atomic_path
    from damcap.common.capture_folder import read_capture
    from damcap.common.colour import preview_gamma

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--model", action="append", required=True, help="NAME=FILE.dam, repeatable (columns in this order)")
    ap.add_argument("--rows", type=int, default=4, help="test views shown, evenly spaced over the test split")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if any("=" not in m for m in args.model):
        ap.error("--model takes NAME=FILE.dam")
    models = {name: load_dam(path)[0] for name, path in (m.split("=", 1) for m in args.model)}
    test = load_views(read_capture(args.capture), "test")
    rows = [test[round(i)] for i in np.linspace(0, len(test) - 1, min(args.rows, len(test)))]
    fig, ax = plt.subplots(len(rows), 1 + len(models), figsize=(2.4 * (1 + len(models)), 2.4 * len(rows)), squeeze=False)
    for i, view in enumerate(rows):
        photo = view.data.radiance_lin
        white = float(np.percentile(photo[view.data.coverage > 0], 99))
        ax[i, 0].imshow(preview_gamma(photo / white))
        ax[i, 0].set_title(f"photo {view.name}", fontsize=9)
        for j, (name, model) in enumerate(models.items()):
            rendered = render_frame(model, view.data, view.centre_world)
            ax[i, j + 1].imshow(preview_gamma(rendered / white))
            ax[i, j + 1].set_title(f"{name}: DSSIM {score_view(view, rendered):.3f}", fontsize=9)
    for a in ax.flat:
        a.axis("off")
    fig.tight_layout()
    with atomic_path(args.out) as tmp:
        fig.savefig(tmp, dpi=50, format="png")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
