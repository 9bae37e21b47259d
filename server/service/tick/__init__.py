"""The tick thread's part, the only thread that touches the World: the tick loop with its one
frame path (``ticker``: commands applied, the step enqueued, the World's wire-ready frame of the
tick before handed to the publisher), the commands queued by the request and cook threads applied
at the start of a tick (``applier``), among them the 1.4 moves blocks (``moves``), and the
adaptive quality it feeds each tick's cost (``adaptive``)."""

__all__ = ["adaptive", "applier", "moves", "ticker"]
