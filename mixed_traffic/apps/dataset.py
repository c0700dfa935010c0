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
import sys
import time

import hydra
from omegaconf import DictConfig, OmegaConf


def run(cfg: DictConfig | dict) -> dict:
    """Validate, generate and write; returns a summary dict."""
    from mixed_traffic.controllers.deeplcc.dataset import DatasetConfig, generate_dataset, write_dataset

    d = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    output, overwrite, progress = d.pop("output"), d.pop("overwrite", True), d.pop("progress", True)
    allowed = {f.name for f in dataclasses.fields(DatasetConfig)}
    unknown = set(d) - allowed
    if unknown:
        raise ValueError(f"mt-dataset: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed | {'output', 'overwrite', 'progress'})}")
    if "brake_start" in d:
        d["brake_start"] = tuple(d["brake_start"])
    dcfg = DatasetConfig(**d).validate()
    if not isinstance(output, str) or not output.endswith(".npz"):
        raise ValueError(f"mt-dataset: output={output!r} is invalid; allowed: a path ending in .npz")
    output = hydra.utils.to_absolute_path(output) if hydra.core.hydra_config.HydraConfig.initialized() else output
    if os.path.exists(output) and not overwrite:
        raise ValueError(f"mt-dataset: output={output!r} exists and overwrite=false; pass overwrite=true or another path")
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
    try:
        run(cfg)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def main() -> None:
    _hydra_main()


if __name__ == "__main__":
    main()
