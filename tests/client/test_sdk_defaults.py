"""The SDK's defaults that a game relying on the README's first example gets (issue 26): failover
on, with an explicit way to turn it off."""

from __future__ import annotations

import inspect

from drape.client import DrapeClient


def test_failover_is_on_by_default_and_can_be_turned_off():
    failover = inspect.signature(DrapeClient).parameters["failover"]
    assert failover.default is True and failover.kind is inspect.Parameter.KEYWORD_ONLY
