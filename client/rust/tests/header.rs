//! include/drape.h is what cbindgen generates from src/ffi/ today: regenerate and compare
//! (set DRAPE_UPDATE_HEADER=1 to rewrite the checked-in header instead).
use std::path::PathBuf;

#[test]
fn checked_in_header_is_current() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(root.join("cbindgen.toml")).expect("cbindgen.toml");
    let mut out = Vec::new();
    cbindgen::Builder::new()
        .with_config(config)
        .with_src(root.join("src/ffi/mod.rs"))
        .generate()
        .expect("cbindgen failed")
        .write(&mut out);
    let generated = String::from_utf8(out).unwrap();
    let path = root.join("include/drape.h");
    if std::env::var_os("DRAPE_UPDATE_HEADER").is_some() {
        std::fs::write(&path, &generated).unwrap();
        return;
    }
    let checked_in = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(checked_in == generated,
            "include/drape.h differs from what cbindgen generates from src/ffi/: run \
             `DRAPE_UPDATE_HEADER=1 cargo test --test header` and commit include/drape.h");
}
