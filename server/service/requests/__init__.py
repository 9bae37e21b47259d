"""The request thread's part: what happens to a query from the moment Zenoh delivers it until it
is answered or handed on. Zenoh's queryable callbacks put queries on the bounded queue
(``requestq``: the queue, the request thread and the gate that keeps it off the tick); the one
request thread runs the handlers (``handlers``: decode, validate, ownership and quotas), checks
1.4 moves blocks on arrival (``moves``) and asks the cost model whether a submission fits
(``admission``: the tick thread feeds it each tick's cost, the request thread asks it). What a
handler accepts goes to the cook thread (submissions) or the tick thread's intake
(drape.server.service.commands)."""

__all__ = ["admission", "handlers", "moves", "requestq"]
