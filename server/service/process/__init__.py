"""The process around a server: ``drape serve`` (``daemon``) and its supervisor of N worker
processes (``workers``, each worker's settings in ``workerplan``), the operator's side (``ops``:
health, readiness, systemd; ``metrics``: Prometheus; ``telemetry``: the tick-phase timers both
and the Zenoh stats read), logging (``logs``) and the process's memory (``memory``: heap
settings, programs released and heap trimmed, the garbage collector kept off the tick)."""

__all__ = ["daemon", "logs", "memory", "metrics", "ops", "telemetry", "workerplan", "workers"]
