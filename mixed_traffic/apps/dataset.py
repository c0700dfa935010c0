"""``mt-dataset``: generate the DeeP-LCC (state, QP solution) dataset (Hydra app).

    mt-dataset                                        # 100 episodes, defaults of hydra_configs/dataset.yaml
    mt-dataset episodes=2 episode_seconds=10 output=/tmp/small.npz
    mt-dataset hdv_model=idm output=outputs/deeplcc/dataset_idm.npz

Every value is validated before any work starts; the output is written
atomically, so a bad value or a failed run never touches an existing file.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time

import hydra
from omegaconf import DictConfig, OmegaConf

from mixed_traffic.validation import ConfigError, check_writable_dir, guarded, run_cli


def estimate_bytes(cfg) -> int:
    """Rough size of the dataset file (float32 windows and Hankel blocks), for the free-space check."""
    m, p = 2, 10  # CAVs and outputs of the DeeP-LCC platoon
    steps = max(1, int(round(cfg.episode_seconds / cfg.dt)) - cfg.t_ini)
    per_sample = 4 * (m * cfg.t_ini + p * cfg.t_ini + cfg.t_ini) + 8 * m + 4
    hankel = 4 * (m + 1 + p) * (cfg.t_ini + cfg.n) * (cfg.T - cfg.t_ini - cfg.n + 1)
    return cfg.episodes * (steps * per_sample + hankel)


def check_output(output: str, overwrite: bool, need_bytes: int = 0) -> None:
    """Before generating: the output's directory is writable, an existing file may be replaced, the disk has room."""
    if os.path.isdir(output):
        raise ConfigError("output", f"{output!r} is a directory", "a file path ending in .npz")
    if os.path.exists(output) and not overwrite:
        raise ConfigError("output", f"{output!r} exists and overwrite=false", "overwrite=true or another path")
    d = check_writable_dir("output", os.path.dirname(os.path.abspath(output)))
    free = shutil.disk_usage(d).free
    if need_bytes > free:
        raise ConfigError("output", f"the dataset needs about {need_bytes / 1e6:.0f} MB and {str(d)!r} has "
                          f"{free / 1e6:.0f} MB free", "a path on a disk with enough free space, or fewer episodes")


def run(cfg: DictConfig | dict) -> dict:
    """Validate, generate and write; returns a summary dict."""
    d = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    output, overwrite, progress = d.pop("output", "outputs/deeplcc/dataset.npz"), d.pop("overwrite", True), \
        d.pop("progress", True)
    if not isinstance(output, str) or not output.endswith(".npz"):
        raise ConfigError("output", f"{output!r} is invalid", "a path ending in .npz")
    output = hydra.utils.to_absolute_path(output) if hydra.core.hydra_config.HydraConfig.initialized() else output
    check_output(output, overwrite)  # before the (slow) imports and the generation

    from mixed_traffic.controllers.deeplcc.dataset import DatasetConfig, generate_dataset, write_dataset

    allowed = {f.name for f in dataclasses.fields(DatasetConfig)}
    unknown = set(d) - allowed
    if unknown:
        raise ConfigError(sorted(unknown)[0], f"unknown key(s) {sorted(unknown)}",
                          str(sorted(allowed | {"output", "overwrite", "progress"})))
    if "brake_start" in d:
        d["brake_start"] = tuple(d["brake_start"])
    dcfg = DatasetConfig(**d).validate()
    check_output(output, overwrite, estimate_bytes(dcfg))
    t0 = time.perf_counter()
    data = generate_dataset(dcfg, progress=progress)
    write_dataset(output, data)
    wall = time.perf_counter() - t0
    summary = {"output": output, "episodes": dcfg.episodes, "samples": int(len(data["u_opt"])),
               "wall_seconds": round(wall, 1), "bytes": os.path.getsize(output)}
    print(f"mt-dataset: wrote {summary['samples']} samples from {dcfg.episodes} episodes to {output} "
          f"({summary['bytes'] / 1e6:.0f} MB) in {wall:.1f} s")
    return summary


@hydra.main(config_path="pkg://hydra_configs", config_name="dataset", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    guarded(lambda: run(cfg), "mt-dataset")


def main(argv: list[str] | DictConfig | None = None):
    """Console entry point: bad input gives ``error: <field>: ...`` and exit status 2 (``MT_DEBUG=1``: traceback).

    Given a composed config instead of an argv (as a ``@hydra.main`` function), runs it directly.
    """
    if isinstance(argv, DictConfig):
        return run(argv)
    run_cli(_hydra_main, "mt-dataset", argv)


if __name__ == "__main__":
    main()
