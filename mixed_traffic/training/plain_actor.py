"""The pipeline actor's network run on plain tensors, without TensorDict bookkeeping per call.

``PlainSequence`` runs a ``TensorDictSequential`` of ``TensorDictModule``s (the actor's
``module[0]``: trunk and Gaussian head) on the tensors of its ``in_keys`` and returns
``(loc, scale)``. The same modules, called in the same order, so the numbers are the actor's
own. Two users: ``torch.func.vmap`` over a population of parameter vectors (the cross-entropy
method, which cannot trace ``TensorDict`` writes) and the analytic-gradient steps, where the
``TensorDictModule`` wrappers (key checks, ``TensorDict.from_any`` on every output) cost more
per step than the small network itself.
"""

from __future__ import annotations

from torch import nn


class PlainSequence(nn.Module):
    """A ``TensorDictSequential`` of ``TensorDictModule``s run on plain tensors; returns ``(loc, scale)``."""

    def __init__(self, seq):
        super().__init__()
        self.seq = seq
        self.in_keys = list(seq.in_keys)

    def forward(self, *inputs):
        values = dict(zip(self.in_keys, inputs))
        for m in self.seq.module:
            out = m.module(*[values[k] for k in m.in_keys])
            values.update(zip(m.out_keys, out if isinstance(out, tuple) else (out,)))
        return values["loc"], values["scale"]


def plain_parts(actor):
    """``(PlainSequence, distribution module)`` of a pipeline ``ProbabilisticActor``, or ``None`` for another module."""
    seq = getattr(actor, "module", None)
    if seq is None or len(seq) != 2 or not hasattr(seq[1], "get_dist"):
        return None
    net = seq[0]
    subs = getattr(net, "module", None)
    if not isinstance(subs, nn.ModuleList) or not all(hasattr(m, "in_keys") and hasattr(m, "out_keys")
                                                       and isinstance(getattr(m, "module", None), nn.Module)
                                                       for m in subs):
        return None
    if not {"loc", "scale"} <= set(net.out_keys) or list(seq[1].in_keys) != ["loc", "scale"]:
        return None
    return PlainSequence(net), seq[1]
