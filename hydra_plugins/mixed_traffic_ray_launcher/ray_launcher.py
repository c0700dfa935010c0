"""Hydra launcher: every job of a multirun is a Ray task, on a local Ray or a cluster.

Why not ``hydra-ray-launcher``: its 1.2.2 release pins ``cloudpickle<3``, which breaks
joblib 1.6 (the Hydra joblib launcher of this project needs ``cloudpickle>=3``); Ray
itself (2.60) installs cleanly. This launcher is the joblib launcher's job runner
(``hydra.core.utils.run_job`` on the job's composed sweep config) with Ray as the
executor: jobs are composed by Hydra exactly as with the basic launcher, the sweep
callbacks (the sweep summary) run in the driver, each job writes to its own
``hydra.sweep.dir/<subdir>`` (on a cluster: a filesystem every node sees).

Config (``hydra_configs/hydra/launcher/ray.yaml``)::

    ray:
      init: {address: null, num_cpus: null}   # ray.init(...): null starts a local Ray; "auto" joins a cluster
      remote: {num_cpus: 1, max_retries: 0}    # ray.remote(...) options of each job

    mt-train -m hydra/launcher=ray seed=0,1,2                          # local Ray
    mt-train -m hydra/launcher=ray hydra.launcher.ray.init.address=auto seed=0,1,2   # on a cluster
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, configure_log, filter_overrides, run_job, setup_globals
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf, open_dict

log = logging.getLogger(__name__)


def execute_job(idx: int, overrides: Sequence[str], hydra_context: HydraContext, config: DictConfig,
                task_function: TaskFunction, singleton_state: dict[Any, Any]) -> JobReturn:
    """One job, inside a Ray worker: compose its sweep config and run the task function."""
    setup_globals()
    Singleton.set_state(singleton_state)
    sweep_config = hydra_context.config_loader.load_sweep_config(config, list(overrides))
    with open_dict(sweep_config):
        sweep_config.hydra.job.id = f"{sweep_config.hydra.job.name}_{idx}"
        sweep_config.hydra.job.num = idx
    HydraConfig.instance().set_config(sweep_config)
    return run_job(hydra_context=hydra_context, config=sweep_config, task_function=task_function,
                   job_dir_key="hydra.sweep.dir", job_subdir_key="hydra.sweep.subdir")


class RayLauncher(Launcher):
    """Runs the jobs of a sweep as Ray tasks (``ray.remote(**remote)``), ``ray.init(**init)`` if needed."""

    def __init__(self, ray: DictConfig | dict | None = None, **_: Any) -> None:
        cfg = OmegaConf.to_container(ray, resolve=True) if isinstance(ray, DictConfig) else dict(ray or {})
        self.init_kwargs = {k: v for k, v in (cfg.get("init") or {}).items() if v is not None}
        self.remote_kwargs = {k: v for k, v in (cfg.get("remote") or {}).items() if v is not None}
        self.config: DictConfig | None = None
        self.task_function: TaskFunction | None = None
        self.hydra_context: HydraContext | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config, self.task_function, self.hydra_context = config, task_function, hydra_context

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        try:
            import ray
        except ImportError:
            raise ImportError("hydra/launcher=ray needs Ray: pip install 'mixed-traffic[ray]'") from None
        setup_globals()
        assert self.config is not None and self.task_function is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        started = not ray.is_initialized()
        if started:
            ray.init(**{"include_dashboard": False, "log_to_driver": True, **self.init_kwargs})
        log.info(f"Ray ({ray.cluster_resources().get('CPU', 0):g} CPUs) is launching {len(job_overrides)} jobs, "
                 f"ray.remote({self.remote_kwargs}); sweep output dir: {sweep_dir}")
        for idx, overrides in enumerate(job_overrides):
            log.info(f"\t#{initial_job_idx + idx} : {' '.join(filter_overrides(overrides))}")
        remote = ray.remote(**self.remote_kwargs)(execute_job) if self.remote_kwargs else ray.remote(execute_job)
        state = Singleton.get_state()
        refs = [remote.remote(initial_job_idx + idx, list(overrides), self.hydra_context, self.config,
                              self.task_function, state)
                for idx, overrides in enumerate(job_overrides)]
        try:
            runs = ray.get(refs)
        finally:
            if started:
                ray.shutdown()
        assert all(isinstance(r, JobReturn) for r in runs)
        return runs
