"""The ``drape`` tools: demo, bench, tradeoff, loadtest, devices (one module per subcommand, with
their helpers: procs, plots, render, loadclient, loadreport, tradeoffrun, tradeoffreport). They
need the ``tools`` extra; never imported by sim or service."""

__all__: list[str] = []  # the subcommands are imported by name (drape.server.cli), never from here
