//! The Drape wire protocol 1.4 (PROTOCOL.md) without any network: key expressions, msgpack
//! requests and replies (1.4's `moves` blocks included; later minors' fields a client sends: 1.7's
//! scene request, 1.8's mesh colliders), the binary state (`DRPS`) and bundle
//! (`DRPB`) payloads, float16 / quant16, the geometry a client needs (grids, OBJ files) and the
//! placement rule of section 11.3. Everything here is pure and
//! allocation-conscious: states decode straight into caller-provided `f32` slices.
pub mod bundle;
pub mod error;
pub mod geometry;
pub mod half;
pub mod keys;
pub mod layout;
pub mod meshcollider;
pub mod moves;
pub mod msg;
mod msg_decode;
pub mod placement;
pub mod predictive;
pub mod reader;
pub mod replies;
pub mod scene;
pub mod state;
pub mod validate;

pub use bundle::{encode_bundle, parse_bundle, Bundle, BundleEntry, BUNDLE_HEADER_SIZE};
pub use error::{Error, ErrorCode, Result};
pub use geometry::{grid_geometry, parse_obj};
pub use keys::{valid_id, valid_namespace, valid_token, Keys, CLIENT_REQUESTS};
pub use meshcollider::{mesh_problem, MeshCollider, MESH_MAX_TRIANGLES, MESH_MAX_VERTICES, MESH_MIN_AREA};
pub use moves::{DecodedBatch, MoveFailed, Moves, MovesReply};
pub use msg::{
    Collider, Control, ControlBatch, Encoding, Grid, Links, Material, Mesh, Orientation, Pins, Resume, Shape,
    StateOptions, Submit,
};
pub use replies::{Applied, BatchItem, BatchReply, ErrorReply, SubmitReply};
pub use placement::{rank, ServerLoad, PLACE_ELSEWHERE};
pub use scene::{SceneReply, SceneRequest};
pub use predictive::{is_predictive, parse_predictive, PredictiveHeader, Stream as PredictiveStream};
pub use validate::Limits;
pub use state::{decode_state_into, encode_state, parse_state, state_size, StateHeader, STATE_HEADER_SIZE};

/// The protocol version this crate speaks and writes: `[1, 4]` (it reads every minor of major 1).
/// Of 1.4 it speaks the client-scoped request keys, `moves` blocks and placement by load, each
/// toward a server whose `info.version` says it has them (older servers get the 1.3 way).
pub const PROTOCOL_MAJOR: u8 = 1;
pub const PROTOCOL_MINOR: u8 = 4;
/// The default namespace and server endpoint.
pub const DEFAULT_NAMESPACE: &str = "drape";
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";
/// State flag bits.
pub const FLAG_NORMALS: u16 = 1;
pub const FLAG_RESET: u16 = 2;
/// Protocol limits a client checks before sending (server defaults, PROTOCOL.md section 13).
pub const MAX_BATCH_ITEMS: usize = 64;
/// 1.4: the most cloths in one `moves` block (fixed: the decoding cap on an array's length).
pub const MAX_BATCH_MOVES: usize = 1024;
pub const MAX_PIN_UPDATES: usize = 4096;
pub const MAX_COLLIDERS: usize = 32;
pub const MAX_FEATURES: usize = 16;
/// The features, in the protocol's canonical order (the order of a reply's `features`).
pub const FEATURE_NAMES: [&str; 6] = ["xpbd", "tethers", "colliders", "wind", "normals", "self_collision"];
pub const QUALITY_PRESETS: [&str; 4] = ["fast", "balanced", "accurate", "exact"];
/// 1.2: the least total `material.mass` (kg); smaller masses make float32 per-vertex masses
/// subnormal or infinite (PROTOCOL.md section 4).
pub const MIN_MASS: f64 = 1.0e-9;
/// 1.5: the predictive encoding's grid `state.step` (metres): its range and the server's default.
pub const STEP_MIN: f64 = 1e-5;
pub const STEP_MAX: f64 = 0.1;
pub const STEP_DEFAULT: f64 = 0.001;
/// 1.2 decoding caps (PROTOCOL.md sections 3 and 13): deeper nesting, more keys in a map, a
/// longer array or string, or an extension type are `malformed`; more values than
/// `MAX_VALUES` in one message is `too_large`. The message map is nesting level 1.
pub const MAX_NESTING: usize = 16;
pub const MAX_MAP_KEYS: usize = 128;
pub const MAX_ARRAY_LENGTH: usize = 1024;
pub const MAX_STRING_BYTES: usize = 1 << 16;
pub const MAX_VALUES: usize = 1 << 16;
