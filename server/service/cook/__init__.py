"""The cook thread's part: accepted submissions turned into what the tick thread adds, off the
tick path (``worker``: fabric, cloth parameters and kernels built before the cloth is added),
the service's one fabric cache (``fabrics``: acquired here, released by the tick thread), the
server's warm-up on a World (``warmup``) and kernel builds in a child process (``buildhelper``),
which warms a scratch World with that same warm-up, never a Server."""

__all__ = ["buildhelper", "fabrics", "warmup", "worker"]
