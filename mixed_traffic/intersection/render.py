"""Frames and GIFs of intersection episodes (matplotlib + imageio).

An episode record is a dict of arrays ``ego`` ``[T, 2]``, ``agent`` ``[T, 2]`` (true centre),
``agent_obs`` ``[T, 2]`` (perceived centre) and ``sigma`` ``[T, 2]``, as
:func:`mixed_traffic.intersection.evaluate.evaluate_policy` keeps for ``record=[...]``.

>>> import numpy as np
>>> ep = {"ego": np.array([[0.5, -1.25], [0.5, -1.1]]), "agent": np.array([[3.0, 0.5], [2.9, 0.5]]),
...       "agent_obs": np.array([[3.0, 0.52], [2.9, 0.49]]), "sigma": np.full((2, 2), 0.05)}
>>> draw_frame(ep, 1).shape[-1]
3
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import imageio.v2 as imageio  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Ellipse, Rectangle  # noqa: E402

RADIUS = 0.3328


def _background(ax, lim=4.0):
    ax.set_facecolor("#5f8f4e")
    ax.add_patch(Rectangle((-lim, -1.0), 2 * lim, 2.0, color="#3a3a3a"))  # east-west road
    ax.add_patch(Rectangle((-1.0, -lim), 2.0, 2 * lim, color="#3a3a3a"))  # north-south road
    ax.add_patch(Rectangle((-1.5, -1.5), 3.0, 3.0, fill=False, ls=":", ec="w", lw=0.8))
    ax.plot([-lim, -1.0], [0, 0], "y--", lw=0.8)
    ax.plot([1.0, lim], [0, 0], "y--", lw=0.8)
    ax.plot([0, 0], [-lim, -1.0], "y--", lw=0.8)
    ax.plot([0, 0], [1.0, lim], "y--", lw=0.8)
    ax.axhline(1.25, xmin=0.5, xmax=0.65, color="lime", lw=1.5)  # goal line for the ego
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def draw_frame(ep: dict, k: int, title: str = "", fig=None) -> np.ndarray:
    """RGB image ``[H, W, 3]`` of step ``k`` of an episode record."""
    own = fig is None
    if own:
        fig = plt.figure(figsize=(3.6, 3.6), dpi=80)
    fig.clf()
    ax = fig.add_axes([0, 0, 1, 0.92])
    _background(ax)
    ego, agent, obs, sig = (np.asarray(ep[key]) for key in ("ego", "agent", "agent_obs", "sigma"))
    k = min(k, len(ego) - 1)
    ax.plot(ego[: k + 1, 0], ego[: k + 1, 1], color="#7fb3ff", lw=1)
    ax.plot(agent[: k + 1, 0], agent[: k + 1, 1], color="#ff9c9c", lw=1)
    ax.add_patch(Circle(ego[k], RADIUS, color="#1f6fe0", zorder=3))
    ax.add_patch(Circle(agent[k], RADIUS, color="#e03a1f", zorder=3))
    s = np.linalg.norm(sig[k])
    ax.add_patch(Ellipse(obs[k], 2 * (RADIUS + 2 * sig[k, 0]), 2 * (RADIUS + 2 * sig[k, 1]), fill=False, ec="orange",
                         ls="--", lw=1.2, zorder=4))
    ax.add_patch(Circle(ego[k], 2 * RADIUS + s, fill=False, ec="#9fd0ff", ls=":", lw=0.8, zorder=2))
    fig.text(0.02, 0.95, f"{title}  t={k * 0.1:.1f}s", fontsize=7)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    if own:
        plt.close(fig)
    return img


def episode_gif(ep: dict, path: str | Path, *, title: str = "", every: int = 2, fps: int = 10) -> Path:
    """Write a GIF of an episode record (every ``every``-th step, plus the last one)."""
    n = len(ep["ego"])
    ks = list(range(0, n, every))
    if ks[-1] != n - 1:
        ks.append(n - 1)
    fig = plt.figure(figsize=(3.6, 3.6), dpi=80)
    try:
        frames = [draw_frame(ep, k, title, fig=fig) for k in ks]
    finally:
        plt.close(fig)
    frames += [frames[-1]] * 5  # hold the outcome
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, frames, duration=1.0 / fps, loop=0)
    return path


__all__ = ["draw_frame", "episode_gif"]
