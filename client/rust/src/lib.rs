//! Drape client: the wire protocol (module [`wire`], no network), rendering between states
//! ([`smoothing`], no network), rates per subscriber and their governor ([`rates`], no network) and, with the default `client` feature, a Zenoh client
//! ([`client`]) and its C ABI ([`ffi`]).
pub mod rates;
pub mod smoothing;
pub mod wire;
#[cfg(feature = "client")]
pub mod client;
#[cfg(feature = "client")]
pub mod ffi;
