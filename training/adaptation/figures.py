"""Figures of docs/adaptation.md.

    python -m tactile_deploy.training.adaptation.figures augmentation [--domain gelslim1] [--out docs/img/adapt_augmentation.png]

``augmentation``: presses of a virtual sensor; per row the clean simulated depth map of the
contact, what the sensor's plugin makes of its camera frame, and three augmentations of the
clean map (``training/configs/cpu_adapt_aug.json``'s settings): the augmentation should span
what the sensor does to the clean map.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def augmentation_figure(domain, out: Path, config: Path, n: int = 5, seed: int = 0) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from tactile_deploy.atomic import atomic_path
    from tactile_deploy.training.augment import Augmenter
    from tactile_deploy.training.config import TrainConfig

    cfg = TrainConfig.load(config).augmentation
    aug = Augmenter(cfg.model_copy(update={"probability": 1.0}))
    rng = np.random.default_rng(seed)
    deep = np.flatnonzero(domain.true_depth_mm.max(axis=(1, 2)) > 0.4)
    pick = rng.choice(deep, size=min(n, len(deep)), replace=False)
    gen = torch.Generator().manual_seed(seed)
    cols = ["simulated (clean)", f"{domain.name} plugin", "augmented 1", "augmented 2", "augmented 3"]
    fig, axes = plt.subplots(len(pick), len(cols), figsize=(2.2 * len(cols), 2.2 * len(pick) + 0.4), squeeze=False)
    for r, i in enumerate(pick):
        clean = torch.as_tensor(domain.true_depth_mm[i])[None].repeat(3, 1, 1)
        augmented = aug(clean, gen).numpy()
        imgs = [domain.true_depth_mm[i], domain.depth_mm[i], *augmented]
        vmax = float(domain.true_depth_mm[i].max())
        for c, img in enumerate(imgs):
            ax = axes[r, c]
            ax.imshow(img, cmap="viridis", vmin=-0.25 * vmax, vmax=1.1 * vmax)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=9)
        axes[r, 0].set_ylabel(f"{domain.indenter[i]}\n{vmax:.2f} mm", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=75)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    from tactile_deploy.training.adaptation.domains import load_or_make

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("figure", choices=["augmentation"])
    ap.add_argument("--domain", default="gelslim1")
    ap.add_argument("--config", type=Path, default=ROOT / "training" / "configs" / "cpu_adapt_aug.json")
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "adapt" / "domains")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "adapt_augmentation.png")
    args = ap.parse_args(argv)
    domain = load_or_make(args.domain, 300, 0, args.work)
    print(augmentation_figure(domain, args.out, args.config))
    return 0


if __name__ == "__main__":
    from tactile_deploy.training.errors import run_command

    raise SystemExit(run_command(main))
