"""The tick thread's part, the only thread that touches the World: the commands queued by the
request and cook threads applied at the start of a tick (``applier``), among them the 1.4 moves
blocks (``moves``)."""

__all__ = ["applier", "moves"]
