"""Checkpoint state of the frontend's components: the attributes a component names, nothing else."""
from __future__ import annotations


class StateFields:
    """state_dict / load_state_dict over the attribute names in `_STATE` (the collaborators a
    component gets in its constructor are not state: a loaded frontend wires its own)."""

    _STATE: tuple[str, ...] = ()

    def state_dict(self) -> dict:
        """What a checkpoint keeps."""
        return {k: getattr(self, k) for k in self._STATE}

    def load_state_dict(self, state: dict) -> None:
        """Restore the named attributes present in state (older checkpoints may lack some)."""
        for k in self._STATE:
            if k in state:
                setattr(self, k, state[k])
