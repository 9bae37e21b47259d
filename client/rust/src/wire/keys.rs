//! Key expressions of PROTOCOL.md section 2 and the id / namespace / token formats.

/// An id (server, client, cloth): 1-64 characters of `[A-Za-z0-9_.-]`.
pub fn valid_id(s: &str) -> bool {
    !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'.' || b == b'-')
}

/// A namespace: one or more ids separated by `/` (at most 8 chunks, as the reference does).
pub fn valid_namespace(s: &str) -> bool {
    let chunks: Vec<&str> = s.split('/').collect();
    chunks.len() <= 8 && chunks.iter().all(|c| valid_id(c))
}

/// An ownership token: 32 lowercase hex digits.
pub fn valid_token(s: &str) -> bool {
    s.len() == 32 && s.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// The key expressions of one namespace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    pub namespace: String,
}

impl Keys {
    pub fn new(namespace: &str) -> Keys {
        Keys { namespace: namespace.to_string() }
    }
    /// A server queryable: `kind` is submit, control, control_batch, remove or info.
    pub fn query(&self, server: &str, kind: &str) -> String {
        format!("{}/server/{server}/{kind}", self.namespace)
    }
    pub fn stats(&self, server: &str) -> String {
        format!("{}/server/{server}/stats", self.namespace)
    }
    pub fn state(&self, cloth: &str) -> String {
        format!("{}/cloth/{cloth}/state", self.namespace)
    }
    pub fn bundle(&self, client: &str) -> String {
        format!("{}/client/{client}/states", self.namespace)
    }
    pub fn alive_server(&self, server: &str) -> String {
        format!("{}/alive/server/{server}", self.namespace)
    }
    pub fn alive_client(&self, client: &str) -> String {
        format!("{}/alive/client/{client}", self.namespace)
    }
    pub fn all_servers_alive(&self) -> String {
        format!("{}/alive/server/*", self.namespace)
    }
    /// The last chunk of a key (the id in a liveliness key).
    pub fn last_chunk(key: &str) -> &str {
        key.rsplit('/').next().unwrap_or(key)
    }
}
