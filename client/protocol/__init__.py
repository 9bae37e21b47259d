"""The Drape wire protocol, version 1.5 (see PROTOCOL.md at the repository root).

Requests and replies are msgpack maps; the per-tick cloth state is a fixed little-endian binary
layout that any language reads with a struct. This package is the single source of truth for
both, one module per job:

- :mod:`.keys`: protocol versions, ids, key expressions;
- :mod:`.errors`: error codes and their exception classes;
- :mod:`.vocabulary`: features, quality presets, encodings, colliders, material fields with their
  ranges and defaults, link options, limits (the server takes its names and defaults from here);
- :mod:`.messages`: every request and reply as a dataclass, and :func:`resolve_features`;
- :mod:`.validate`: msgpack framing with hostile-input caps and the typed field readers;
- :mod:`.codec`: ``encode_*`` / ``decode_*`` of every msgpack message;
- :mod:`.state` and :mod:`.bundle`: the binary ``DRPS`` state and ``DRPB`` bundle layouts with the
  float16 / quant16 arithmetic; :mod:`.predictive`: the predictive encoding's codec (1.5) and
  :mod:`.stream`: a cloth's stream of states decoded in order (predictive states need it);
- :mod:`.geometry`: grid geometry and OBJ parsing;
- :mod:`.schemagen`: JSON Schemas of the msgpack maps and the C header of the binary layouts,
  generated from the modules above (``client/protocol/schema/``, ``client/protocol/drape_wire.h``).

Every public name of every module is re-exported here, so ``from drape.client import protocol as P``
then ``P.<name>`` works for all of them. 1.1 added state bundles and batch control; 1.2 adds
``features_add`` / ``features_remove`` in controls, the resulting ``features`` in control replies,
the ``overloaded`` error code and documented decoding caps; 1.3 adds ``resume`` in submissions
(:class:`ResumeState`: continue a cloth from its last state after a failover; PROTOCOL.md 4.1, 11.1);
1.4 adds ``moves`` in batch controls (:class:`PinMoves`, :mod:`.moves`: many cloths' pin moves as
one columnar block; PROTOCOL.md 5.1.1); 1.5 adds the ``predictive`` state encoding (a state coded
against the last two its decoders rebuilt: PROTOCOL.md 9.2) and ``state.step``.

It imports only numpy, msgpack and the standard library, so a game client or a tool can use it
without Zenoh or OpenCL installed.
"""

from __future__ import annotations

from .bundle import *  # noqa: F401,F403
from .codec import *  # noqa: F401,F403
from .errors import *  # noqa: F401,F403
from .geometry import *  # noqa: F401,F403
from .keys import *  # noqa: F401,F403
from .messages import *  # noqa: F401,F403
from .moves import *  # noqa: F401,F403
from .predictive import *  # noqa: F401,F403
from .state import *  # noqa: F401,F403
from .stream import *  # noqa: F401,F403
from .validate import *  # noqa: F401,F403
from .vocabulary import *  # noqa: F401,F403
