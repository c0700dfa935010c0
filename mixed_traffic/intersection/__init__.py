"""Unsignalised intersection: agent model, NMPC, residual NMPC, evaluation, rendering, training.

Modules: ``agent_model`` (generative human driver + recorded-trajectory loader), ``nmpc``
(CasADi/IPOPT controller as a TensorDict policy), ``residual`` (residual action around the
NMPC), ``evaluate`` (fixed, seeded test set and per-behaviour tables), ``render`` (GIFs),
``train_lppo`` (LPPO, LPPO+BC, LPPO+BFF, residual MPC), ``report`` (tables + GIFs of all runs).
The environment is
:mod:`mixed_traffic.envs.intersection`; the barrier force transform is
:mod:`transforms.barrier_force`.

>>> from mixed_traffic.intersection.agent_model import make_test_set
>>> len(make_test_set(2, horizon=10))
8
"""
