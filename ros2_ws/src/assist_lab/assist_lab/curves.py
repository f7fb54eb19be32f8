"""Learning-curve figures next to a training run's metrics CSV (matplotlib, imported only when drawing)."""
from __future__ import annotations

import csv
import logging
import math
from collections.abc import Sequence
from pathlib import Path

from assist_common.atomic import atomic_path

log = logging.getLogger(__name__)


def _number(text: str | None) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def plot_curves(csv_path: str | Path, png_path: str | Path, x: str, panels: Sequence[Sequence[str]],
                title: str = '', smooth: int = 1) -> bool:
    """Draw columns of `csv_path` against column `x`, one panel per group of `panels`, into `png_path`
    (replaced atomically). `smooth` > 1 adds a running mean over that many rows. Columns the file lacks
    are left out; False (nothing written) when the file has no rows or none of the columns."""
    path = Path(csv_path)
    if not path.is_file():
        return False
    with open(path, newline='', encoding='utf-8') as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return False
    columns = set(rows[0])
    panels = [[c for c in group if c in columns] for group in panels]
    panels = [group for group in panels if group]
    if x not in columns or not panels:
        return False
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import numpy as np
    xs = np.array([_number(r[x]) for r in rows])
    fig, axes = plt.subplots(len(panels), 1, figsize=(6.4, 2.4 * len(panels) + 0.6), sharex=True, squeeze=False)
    for ax, group in zip(axes[:, 0], panels):
        for col in group:
            ys = np.array([_number(r[col]) for r in rows])
            if smooth > 1 and len(ys) >= smooth:
                line, = ax.plot(xs, ys, alpha=0.3, lw=0.8)
                kernel = np.ones(smooth) / smooth
                ax.plot(xs[smooth - 1:], np.convolve(np.nan_to_num(ys), kernel, mode='valid'),
                        color=line.get_color(), label=f'{col} (mean of {smooth})')
            else:
                ax.plot(xs, ys, marker='o' if len(ys) < 50 else None, ms=3, label=col)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[-1, 0].set_xlabel(x)
    if title:
        axes[0, 0].set_title(title)
    fig.tight_layout()
    with atomic_path(Path(png_path)) as tmp:
        fig.savefig(tmp, dpi=110, format='png')
    plt.close(fig)
    return True
