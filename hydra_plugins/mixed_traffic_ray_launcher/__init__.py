"""Hydra launcher running each multirun job as a Ray task (``hydra/launcher=ray``)."""
