"""Error codes (PROTOCOL.md section 8) and the exception class of each."""

from __future__ import annotations

ERR_MALFORMED = "malformed"  # not a msgpack map (truncated, garbage, trailing bytes)
ERR_UNSUPPORTED_VERSION = "unsupported_version"  # unknown major version
ERR_MISSING_FIELD = "missing_field"
ERR_INVALID_TYPE = "invalid_type"
ERR_INVALID_VALUE = "invalid_value"  # non-finite, out of range, unknown name, bad combination
ERR_INDEX_OUT_OF_RANGE = "index_out_of_range"
ERR_TOO_LARGE = "too_large"  # message bytes or an array beyond the protocol caps
ERR_LIMIT_EXCEEDED = "limit_exceeded"  # server quota: cloths, cloths per client, total vertices
ERR_NOT_FOUND = "not_found"  # no such cloth on this server
ERR_FORBIDDEN = "forbidden"  # the token does not own the cloth
ERR_BUSY = "busy"  # request queue full, or the server is shutting down
ERR_INTERNAL = "internal"
ERR_UNAVAILABLE = "unavailable"  # client side only: no server answered in time
ERR_OVERLOADED = "overloaded"  # 1.2, submit: admitting the cloth would break the tick budget; retry later or elsewhere

ERROR_CODES = (
    ERR_MALFORMED,
    ERR_UNSUPPORTED_VERSION,
    ERR_MISSING_FIELD,
    ERR_INVALID_TYPE,
    ERR_INVALID_VALUE,
    ERR_INDEX_OUT_OF_RANGE,
    ERR_TOO_LARGE,
    ERR_LIMIT_EXCEEDED,
    ERR_NOT_FOUND,
    ERR_FORBIDDEN,
    ERR_BUSY,
    ERR_INTERNAL,
    ERR_UNAVAILABLE,
    ERR_OVERLOADED,
)
#: The codes that say the request itself is wrong (a client bug or hostile input: "bad request").
BAD_REQUEST_CODES = (
    ERR_MALFORMED,
    ERR_UNSUPPORTED_VERSION,
    ERR_MISSING_FIELD,
    ERR_INVALID_TYPE,
    ERR_INVALID_VALUE,
    ERR_INDEX_OUT_OF_RANGE,
    ERR_TOO_LARGE,
)


class DrapeError(Exception):
    """Any error reported by a Drape server (or by the SDK on its behalf): a stable ``code``
    from ERROR_CODES and a human-readable ``message``."""

    default_code = ERR_INTERNAL

    def __init__(self, code: str | None = None, message: str = "", rid: int | None = None) -> None:
        self.code = code or self.default_code
        self.message = message
        self.rid = rid
        super().__init__(f"[{self.code}] {message}")


class ProtocolError(DrapeError):
    """A message breaks the protocol: malformed, wrong version, wrong type or value, too large."""

    default_code = ERR_INVALID_VALUE


class LimitExceeded(DrapeError):
    default_code = ERR_LIMIT_EXCEEDED


class NotFound(DrapeError):
    default_code = ERR_NOT_FOUND


class Forbidden(DrapeError):
    default_code = ERR_FORBIDDEN


class Busy(DrapeError):
    default_code = ERR_BUSY


class Unavailable(DrapeError):
    default_code = ERR_UNAVAILABLE


class InternalError(DrapeError):
    default_code = ERR_INTERNAL


class Overloaded(DrapeError):
    """1.2: the server cannot admit this cloth without breaking its tick budget; retry later or
    on another server."""

    default_code = ERR_OVERLOADED


_ERROR_CLASSES: dict[str, type[DrapeError]] = {
    ERR_LIMIT_EXCEEDED: LimitExceeded,
    ERR_NOT_FOUND: NotFound,
    ERR_FORBIDDEN: Forbidden,
    ERR_BUSY: Busy,
    ERR_UNAVAILABLE: Unavailable,
    ERR_INTERNAL: InternalError,
    ERR_OVERLOADED: Overloaded,
}


def error_for(code: str, message: str, rid: int | None = None) -> DrapeError:
    """The DrapeError subclass for a code (ProtocolError for every validation code)."""
    cls = _ERROR_CLASSES.get(code, ProtocolError if code in BAD_REQUEST_CODES else DrapeError)
    return cls(code, message, rid)
