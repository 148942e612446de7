"""Checkpoint state of the frontend's components: the attributes a component names, nothing else."""
from __future__ import annotations


class StateFields:
    """The attributes named in `_STATE` are the component's state (the collaborators it gets in
    its constructor are not: a loaded frontend wires its own). `state_fields()` gives their live
    values, which segs.slam.orb_state encodes as arrays; `load_state_dict` sets decoded ones."""

    _STATE: tuple[str, ...] = ()

    def state_fields(self) -> dict:
        """name -> live value of each state attribute."""
        return {k: getattr(self, k) for k in self._STATE}

    def load_state_dict(self, state: dict) -> None:
        """Restore the named attributes present in state (older checkpoints may lack some)."""
        for k in self._STATE:
            if k in state:
                setattr(self, k, state[k])
