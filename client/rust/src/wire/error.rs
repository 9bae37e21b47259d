//! Error codes of PROTOCOL.md section 8 (1.2: `overloaded`) plus the client-side ones, and the
//! crate's error type.
use std::fmt;

/// An error code: the protocol's codes (same names, PROTOCOL.md section 8) and client-side ones.
/// The numeric values are the C ABI's `DRAPE_E_*` codes (0 is success there).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(i32)]
pub enum ErrorCode {
    Malformed = 1,
    UnsupportedVersion = 2,
    MissingField = 3,
    InvalidType = 4,
    InvalidValue = 5,
    IndexOutOfRange = 6,
    TooLarge = 7,
    LimitExceeded = 8,
    NotFound = 9,
    Forbidden = 10,
    Busy = 11,
    Internal = 12,
    /// Client side: no server answered in time (Zenoh timeout, no queryable, no server seen).
    Unavailable = 13,
    /// Client side: the cloth's server lost its liveliness token (the server is gone).
    ServerLost = 14,
    /// Client side: the client or the cloth was closed / removed.
    Closed = 15,
    /// A code this version does not know (a later minor version may add codes): an error.
    Unknown = 16,
    /// 1.2 (submit): the server cannot admit the cloth without breaking its tick budget; retry
    /// later or on another server. (Numbered after the 1.1 codes so that no code changes.)
    Overloaded = 17,
}

impl ErrorCode {
    pub const ALL: [ErrorCode; 17] = [
        Self::Malformed, Self::UnsupportedVersion, Self::MissingField, Self::InvalidType, Self::InvalidValue,
        Self::IndexOutOfRange, Self::TooLarge, Self::LimitExceeded, Self::NotFound, Self::Forbidden, Self::Busy,
        Self::Internal, Self::Unavailable, Self::ServerLost, Self::Closed, Self::Unknown, Self::Overloaded,
    ];

    /// Whether the request itself is wrong (PROTOCOL.md section 8: `malformed` to `too_large`;
    /// retrying it unchanged gets the same answer).
    pub fn is_bad_request(self) -> bool {
        (self as i32) <= Self::TooLarge as i32
    }

    /// Whether the server cannot take the request now (`limit_exceeded`, `busy`, `overloaded`):
    /// retry later or elsewhere.
    pub fn is_retryable(self) -> bool {
        matches!(self, Self::LimitExceeded | Self::Busy | Self::Overloaded)
    }

    /// The wire name (`"malformed"`, ...); client-side codes have names too.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Malformed => "malformed",
            Self::UnsupportedVersion => "unsupported_version",
            Self::MissingField => "missing_field",
            Self::InvalidType => "invalid_type",
            Self::InvalidValue => "invalid_value",
            Self::IndexOutOfRange => "index_out_of_range",
            Self::TooLarge => "too_large",
            Self::LimitExceeded => "limit_exceeded",
            Self::NotFound => "not_found",
            Self::Forbidden => "forbidden",
            Self::Busy => "busy",
            Self::Internal => "internal",
            Self::Unavailable => "unavailable",
            Self::ServerLost => "server_lost",
            Self::Closed => "closed",
            Self::Unknown => "unknown",
            Self::Overloaded => "overloaded",
        }
    }

    /// The code of a wire name; unknown names map to [`ErrorCode::Unknown`].
    pub fn from_name(name: &str) -> ErrorCode {
        Self::ALL.iter().copied().find(|c| c.as_str() == name).unwrap_or(Self::Unknown)
    }
}

/// An error: its code, a message naming the problem and the request id it answers (0 if none).
#[derive(Debug, Clone, PartialEq)]
pub struct Error {
    pub code: ErrorCode,
    pub message: String,
    pub rid: u64,
}

impl Error {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Error {
        Error { code, message: message.into(), rid: 0 }
    }
    pub fn with_rid(mut self, rid: u64) -> Error {
        self.rid = rid;
        self
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.code.as_str(), self.message)
    }
}

impl std::error::Error for Error {}

pub type Result<T> = std::result::Result<T, Error>;

/// Shorthands used across the crate.
pub(crate) fn malformed(msg: impl Into<String>) -> Error {
    Error::new(ErrorCode::Malformed, msg)
}
pub(crate) fn invalid(msg: impl Into<String>) -> Error {
    Error::new(ErrorCode::InvalidValue, msg)
}
