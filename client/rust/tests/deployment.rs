//! The client id from the deployment (PROTOCOL.md 11.2): with no `client_id` given, the client
//! takes `$DRAPE_CLIENT_ID` and uses it in its 1.4 request keys and state keys. Its own test
//! binary: the environment variable would give every client of the other tests the same id.
mod common;

use drape::client::{Client, ClientOptions, CLIENT_ID_ENV};
use drape::wire::{Grid, Keys, Shape, Submit};
use std::time::{Duration, Instant};

#[test]
fn client_id_from_drape_client_id() {
    let Some(bin) = common::drape_bin() else { return };
    let s = common::start(&bin, &["--identity", "keys"]);
    let id = format!("deployed-{}", std::process::id());
    std::env::set_var(CLIENT_ID_ENV, format!(" {id}\n"));
    let opts = ClientOptions { connect: vec![s.endpoint.clone()], server_id: Some(s.id.clone()), timeout: Duration::from_secs(60), ..Default::default() };
    let client = Client::open(opts).unwrap();
    assert_eq!(client.client_id(), id);
    let given = Client::open(ClientOptions { client_id: Some("given".into()), connect: vec![s.endpoint.clone()], ..Default::default() }).unwrap();
    assert_eq!(given.client_id(), "given", "a given id wins over the environment");
    given.close(false);
    let cloth = client.submit_grid(Grid::new(4, 4), Submit { pinned: vec![0, 3], ..Submit::new("", Shape::Grid(Grid::new(1, 1))) }).unwrap();
    assert_eq!(cloth.state_key(), Keys::new("drape").client_state(&id, &cloth.id()));
    let mut pos = vec![0f32; 48];
    let t0 = Instant::now();
    while cloth.wait_state(&mut pos, None, Duration::from_secs(1)).unwrap().is_none() {
        assert!(t0.elapsed() < common::WAIT, "no state; server log:\n{}", s.log_text());
    }
    cloth.remove().unwrap();
    client.close(true);
}
