"""mixed-traffic: a TorchRL pipeline for safe control of connected automated vehicles.

>>> from mixed_traffic import make_env
>>> env = make_env("ring", batch_size=4, seed=0)
"""

from mixed_traffic.envs import make_env

__version__ = "0.1.0"
__all__ = ["make_env", "__version__"]
