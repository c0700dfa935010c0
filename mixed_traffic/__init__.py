"""mixed-traffic: a TorchRL pipeline for safe control of connected automated vehicles.

>>> from mixed_traffic import make_env
>>> env = make_env("ring", batch_size=4, seed=0)
"""

__version__ = "0.1.0"
__all__ = ["make_env", "__version__"]


def __getattr__(name: str):
    # imported on first use, so the apps can report a bad argument before torch/torchrl load
    if name == "make_env":
        from mixed_traffic.envs import make_env

        return make_env
    raise AttributeError(f"module 'mixed_traffic' has no attribute {name!r}")
