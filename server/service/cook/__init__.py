"""The cook thread's part: accepted submissions turned into what the tick thread adds, off the
tick path (``worker``: fabrics, cloth parameters, kernels built before the cloth is added; the
service's one fabric cache) and kernel builds in a child process (``buildhelper``), which warms
a scratch World with the server's own warm-up (``warmup``), never a Server."""

__all__ = ["buildhelper", "warmup", "worker"]
