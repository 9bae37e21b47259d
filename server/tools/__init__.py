"""The ``drape`` tools: demo, bench, tradeoff, loadtest, devices. Never imported by sim or service."""
