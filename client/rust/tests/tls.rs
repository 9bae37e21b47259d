//! TLS (feature `tls`, on by default): a real `drape serve` listening on `tls/127.0.0.1:PORT`
//! with a certificate made here by `openssl` for a CA made here; the client, given only that
//! endpoint and a Zenoh configuration file naming the CA, submits a cloth and receives its
//! states. A client trusting another CA finds no server (the handshake fails): the link is
//! verified, not merely encrypted.
#![cfg(feature = "tls")]
mod common;
use drape::client::{Client, ClientOptions};
use drape::wire::{Grid, Shape, Submit};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

fn openssl(dir: &Path, args: &[&str]) {
    let out = Command::new("openssl").args(args).current_dir(dir).output().expect("openssl is needed for the TLS test");
    assert!(out.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

fn ca(dir: &Path, name: &str) {
    openssl(dir, &["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", &format!("/CN={name}"),
                   "-keyout", &format!("{name}-key.pem"), "-out", &format!("{name}.pem")]);
}

fn client_config(dir: &Path, ca: &str) -> std::path::PathBuf {
    let file = dir.join(format!("client-{ca}.json5"));
    std::fs::write(&file, format!(r#"{{ transport: {{ link: {{ tls: {{ root_ca_certificate: "{}", verify_name_on_connect: true }} }} }} }}"#,
                                  dir.join(format!("{ca}.pem")).display())).unwrap();
    file
}

#[test]
fn tls_endpoint_verified_by_its_ca() {
    let Some(bin) = common::drape_bin() else { return };
    let dir = std::env::temp_dir().join(format!("drape-tls-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    ca(&dir, "ca");
    ca(&dir, "other-ca");
    openssl(&dir, &["req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost", "-keyout", "server-key.pem", "-out", "server.csr"]);
    std::fs::write(dir.join("server.ext"), "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth\n").unwrap();
    openssl(&dir, &["x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial", "-days", "2",
                    "-extfile", "server.ext", "-out", "server.pem"]);
    let server_cfg = dir.join("server.json5");
    std::fs::write(&server_cfg, format!(r#"{{ transport: {{ link: {{ tls: {{ listen_private_key: "{}", listen_certificate: "{}" }} }} }} }}"#,
                                        dir.join("server-key.pem").display(), dir.join("server.pem").display())).unwrap();
    let port = common::free_port();
    let tls = format!("tls/localhost:{port}");
    let server = common::start(&bin, &["--zenoh-config", server_cfg.to_str().unwrap(), "--listen", &format!("tls/127.0.0.1:{port}")]);

    let opts = |ca: &str, timeout| ClientOptions {
        connect: vec![tls.clone()],
        zenoh_config_file: Some(client_config(&dir, ca)),
        timeout,
        require_server: true,
        ..Default::default()
    };
    let client = match Client::open(opts("ca", Duration::from_secs(120))) {
        Ok(c) => c,
        Err(e) => panic!("no server over {tls}: {e}; server log:\n{}", server.log_text()),
    };
    let cloth = client.submit_grid(Grid::new(4, 4), Submit::new("", Shape::Grid(Grid::new(4, 4)))).expect("submit over TLS");
    let mut pos = vec![0f32; 48];
    let t0 = Instant::now();
    let mut got = None;
    while got.is_none() && t0.elapsed() < Duration::from_secs(30) {
        got = cloth.wait_state(&mut pos, None, Duration::from_millis(200)).unwrap();
    }
    assert!(got.is_some(), "no state over TLS");
    cloth.remove().unwrap();
    client.close(true);

    // trusting another CA: the handshake fails, no server is ever seen
    let e = Client::open(opts("other-ca", Duration::from_secs(3))).err().expect("a client trusting another CA connected");
    assert_eq!(e.code, drape::wire::ErrorCode::Unavailable, "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
