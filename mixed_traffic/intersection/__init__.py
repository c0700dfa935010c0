"""Unsignalised intersection: agent model, NMPC, residual NMPC, evaluation, rendering, training.

Modules: ``nmpc``
(CasADi/IPOPT controller as a TensorDict policy), ``residual`` (residual action around the
NMPC), ``evaluate`` (fixed, seeded test set and per-behaviour tables), ``render`` (GIFs),
``demos`` (cached NMPC demonstrations for behaviour cloning), ``report`` (tables + GIFs of all runs).
The learners (LPPO, LPPO+BC, LPPO+BFF, residual MPC) train in the shared loop
(``mt-train experiment=intersection_*``); the agent model is
:mod:`mixed_traffic.envs.intersection_agents`.
The environment is
:mod:`mixed_traffic.envs.intersection`; the barrier force transform is
:mod:`transforms.barrier_force`.

>>> from mixed_traffic.envs.intersection_agents import make_test_set
>>> len(make_test_set(2, horizon=10))
8
"""
