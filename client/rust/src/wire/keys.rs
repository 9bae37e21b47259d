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

/// The requests a 1.4 client sends on its own client-scoped key (PROTOCOL.md 11.2; `info` stays
/// server-wide: a client asks it before it knows the server's version).
/// 1.7's `scene` request too (sent only to a server of 1.7 or later).
pub const CLIENT_REQUESTS: [&str; 5] = ["submit", "control", "control_batch", "remove", "scene"];

/// The key expressions of one namespace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    pub namespace: String,
}

impl Keys {
    pub fn new(namespace: &str) -> Keys {
        Keys { namespace: namespace.to_string() }
    }
    /// A server-wide queryable (1.0-1.3): `kind` is submit, control, control_batch, remove or info.
    pub fn query(&self, server: &str, kind: &str) -> String {
        format!("{}/server/{server}/{kind}", self.namespace)
    }
    /// 1.4: client `client`'s own request queryable on `server`,
    /// `{ns}/server/{server}/client/{client}/{kind}`, `kind` one of [`CLIENT_REQUESTS`] (the server
    /// takes the request's client id from this key, PROTOCOL.md 11.2).
    pub fn client_request(&self, server: &str, client: &str, kind: &str) -> String {
        debug_assert!(CLIENT_REQUESTS.contains(&kind), "no client-scoped {kind:?} request");
        format!("{}/server/{server}/client/{client}/{kind}", self.namespace)
    }
    /// 1.4: the state key of a cloth submitted on a client-scoped key (clients take it from the
    /// submit reply's `key` and never compute it; here for tests and tools).
    pub fn client_state(&self, client: &str, cloth: &str) -> String {
        format!("{}/client/{client}/cloth/{cloth}/state", self.namespace)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_of_every_version() {
        let k = Keys::new("drape/eu");
        assert_eq!(k.query("s1", "submit"), "drape/eu/server/s1/submit");
        assert_eq!(k.query("s1", "info"), "drape/eu/server/s1/info");
        for kind in CLIENT_REQUESTS {
            assert_eq!(k.client_request("s1", "game-7", kind), format!("drape/eu/server/s1/client/game-7/{kind}"));
        }
        assert_eq!(k.client_state("game-7", "c0"), "drape/eu/client/game-7/cloth/c0/state");
        assert_eq!(k.bundle("game-7"), "drape/eu/client/game-7/states");
    }
}
