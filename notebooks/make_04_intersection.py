"""Generate notebooks/04_intersection.ipynb with nbformat: `python notebooks/make_04_intersection.py`."""
from pathlib import Path

import nbformat as nbf

NOTEBOOK = Path(__file__).resolve().parent / "04_intersection.ipynb"


def build_notebook():
    """The notebook object (cells below)."""
    nb = nbf.v4.new_notebook()
    md, code = nbf.v4.new_markdown_cell, nbf.v4.new_code_cell
    nb.cells = [
        md("# 04 · Unsignalised intersection: NMPC and LPPO\n\n"
           "The ego drives north on `x = 0.5` from `y = -1.25` to `y >= 1.25` while a human-driven agent "
           "(generative model: straight, left, right; zig-zag held out) crosses its path with uncertain "
           "perceived position. This notebook runs the CasADi NMPC and a small-budget Lagrangian PPO on a few "
           "test episodes and shows frames. With `MT_SMALL_BUDGET=1` it finishes in well under 90 s."),
        code("import os, time\n"
             "import numpy as np, torch, matplotlib.pyplot as plt\n"
             "torch.set_num_threads(1)\n"
             "SMALL = os.environ.get('MT_SMALL_BUDGET', '0') == '1'\n"
             "from mixed_traffic import make_env\n"
             "from torchrl.envs.utils import check_env_specs\n"
             "env = make_env('intersection', batch_size=4, seed=0)\n"
             "check_env_specs(env)\n"
             "td = env.reset()\n"
             "print('observation [y, v, x_a, y_a, vx_a, vy_a, sx, sy]:', td['observation'][0].numpy().round(2))\n"
             "print('reward keys:', env.reward_keys)"),
        md("## The agent model\nEach behaviour's true paths (a few samples) and the perceived sigma over time."),
        code("from mixed_traffic.envs.intersection_agents import make_test_set, BEHAVIOURS\n"
             "bank = make_test_set(5, seed=1, horizon=120)\n"
             "fig, ax = plt.subplots(1, 2, figsize=(9, 4))\n"
             "colors = dict(zip(range(4), ['C0', 'C1', 'C2', 'C3']))\n"
             "for i in range(len(bank)):\n"
             "    b = int(bank.behaviour[i])\n"
             "    tr = bank.true[i, :, :2].numpy()\n"
             "    ax[0].plot(tr[:, 0], tr[:, 1], color=colors[b], lw=1, label=BEHAVIOURS[b] if i < 4 else None)\n"
             "    ax[1].plot(np.arange(121) * 0.1, bank.observed[i, :, 4].numpy(), color=colors[b], lw=0.8)\n"
             "ax[0].axvline(0.5, color='k', ls='--', lw=0.8); ax[0].set_xlim(-4, 6); ax[0].set_ylim(-4, 4)\n"
             "ax[0].set_aspect('equal'); ax[0].legend(fontsize=7); ax[0].set_title('agent paths (ego on x = 0.5)')\n"
             "ax[1].set_xlabel('t (s)'); ax[1].set_title('perceived sigma_x (m)')\n"
             "plt.show()"),
        md("## NMPC (CasADi Opti + IPOPT, horizon 30)\nOne test episode per behaviour; the same harness "
           "evaluates every method on the fixed test set."),
        code("from mixed_traffic.intersection.nmpc import make_nmpc_policy\n"
             "from mixed_traffic.intersection.evaluate import evaluate_policy, format_table\n"
             "from IPython.display import Markdown, display\n"
             "t0 = time.time()\n"
             "nmpc = make_nmpc_policy()\n"
             "res = evaluate_policy(nmpc, n_per_behaviour=1 if SMALL else 20, record=[0, 1, 2, 3])\n"
             "display(Markdown(format_table(res.table, title='NMPC')))\n"
             "print({k: round(v, 2) if isinstance(v, float) else v for k, v in res.extra['nmpc'].items()},\n"
             "      f'{time.time() - t0:.1f} s')"),
        code("from mixed_traffic.intersection.render import draw_frame\n"
             "fig, axes = plt.subplots(2, 4, figsize=(12, 6))\n"
             "for col, (i, fr) in enumerate(sorted(res.frames.items())):\n"
             "    n = len(fr['ego'])\n"
             "    for row, k in enumerate([n // 2, n - 1]):\n"
             "        axes[row, col].imshow(draw_frame(fr, k, title=fr['behaviour']))\n"
             "        axes[row, col].axis('off')\n"
             "plt.tight_layout(); plt.show()"),
        md("## Lagrangian PPO (dual critics), small budget\nThe full runs use "
           "`mt-train experiment=intersection_lppo` (see docs/intersection.md); here the same config on a small budget."),
        code("import tempfile\n"
             "from mixed_traffic.config import compose\n"
             "from mixed_traffic.training import train\n"
             "t0 = time.time()\n"
             "cfg = compose(['experiment=intersection_lppo', f'trainer.total_frames={8192 if SMALL else 400_000}',\n"
             "               f'trainer.num_envs={64 if SMALL else 256}', f'trainer.epochs={2 if SMALL else 4}',\n"
             "               'trainer.minibatch_size=1024', 'trainer.progress=false', 'logger=none'])\n"
             "out = train(cfg, out_dir=tempfile.mkdtemp())\n"
             "print(f'trained {out[\"summary\"][\"frames\"]} frames in {time.time() - t0:.1f} s')\n"
             "res_rl = evaluate_policy(out['actor'], n_per_behaviour=1 if SMALL else 20, record=[0])\n"
             "display(Markdown(format_table(res_rl.table, title='LPPO (small budget)')))"),
        code("fr = res_rl.frames[0]\n"
             "n = len(fr['ego'])\n"
             "fig, axes = plt.subplots(1, 3, figsize=(9, 3))\n"
             "for ax, k in zip(axes, [0, n // 2, n - 1]):\n"
             "    ax.imshow(draw_frame(fr, k, title='LPPO')); ax.axis('off')\n"
             "plt.show()"),
    ]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    return nb


if __name__ == "__main__":
    nbf.write(build_notebook(), str(NOTEBOOK))
    print(f"written {NOTEBOOK}")
