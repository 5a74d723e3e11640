"""The matplotlib set-up shared by every picture the project draws (previews, weather panels,
OPE curves, robustness plots). Matplotlib is imported lazily: most users never plot."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from envs.files import atomic_path


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the file-only Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int) -> Path:
    """Write ``fig`` to ``path`` atomically in the format its suffix names (PNG without one;
    parent folders created), close it, return the path."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:  # the temporary's name has no format suffix
        fig.savefig(tmp, dpi=dpi, format=Path(path).suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    return Path(path)
