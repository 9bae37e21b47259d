//! The crate's binary layouts against `client/protocol/drape_wire.h`, the packed C structs the
//! Python package generates (PROTOCOL.md section 16): the header's structs and fields are read
//! from the header itself, a C program compiled with `cc` prints every `offsetof` / `sizeof`
//! and every constant, and each must equal `drape::wire::layout` and the crate's constants. A
//! field or constant added to the header and unknown here fails the test.
use drape::wire::layout::{self, Field};
use drape::wire::{half, Encoding, FLAG_NORMALS, FLAG_RESET, PROTOCOL_MAJOR, PROTOCOL_MINOR};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Command;

fn header_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../protocol/drape_wire.h")
}

/// A struct's name and its field names in order.
type Struct = (String, Vec<String>);

/// The structs and the #define (name, value) pairs, parsed from the header.
fn parse_header(text: &str) -> (Vec<Struct>, Vec<(String, String)>) {
    let mut structs = Vec::new();
    let mut defines = Vec::new();
    let mut current: Option<Struct> = None;
    for line in text.lines() {
        let code = line.split("/*").next().unwrap().trim();
        if let Some(rest) = code.strip_prefix("#define ") {
            let mut it = rest.splitn(2, char::is_whitespace);
            let (name, value) = (it.next().unwrap(), it.next().unwrap_or("").trim());
            if !value.is_empty() {
                defines.push((name.to_string(), value.to_string()));
            }
        } else if let Some(rest) = code.strip_prefix("typedef struct ") {
            current = Some((rest.trim_end_matches('{').trim().to_string(), Vec::new()));
        } else if code.starts_with('}') {
            if let Some(s) = current.take() {
                structs.push(s);
            }
        } else if let (Some((_, fields)), true) = (current.as_mut(), code.ends_with(';')) {
            let decl = code.trim_end_matches(';');
            let name = decl.split_whitespace().last().unwrap().split('[').next().unwrap();
            fields.push(name.to_string());
        }
    }
    (structs, defines)
}

fn rust_layout(name: &str) -> (&'static [Field], usize) {
    match name {
        "drape_state_header" => (&layout::state::FIELDS, layout::state::SIZE),
        "drape_bundle_header" => (&layout::bundle::FIELDS, layout::bundle::SIZE),
        "drape_bundle_entry" => (&layout::entry::FIELDS, layout::entry::SIZE),
        other => panic!("drape_wire.h has a struct {other} this crate does not know: add its layout"),
    }
}

/// The crate's value of each constant of the header, as the C program prints it (numbers as
/// `%f`, strings as they are).
fn rust_constants() -> BTreeMap<&'static str, String> {
    let magic = |m: &[u8; 4]| String::from_utf8(m.to_vec()).unwrap();
    let num = |x: f64| format!("{x:.6}");
    BTreeMap::from([
        ("DRAPE_PROTOCOL_MAJOR", num(PROTOCOL_MAJOR as f64)),
        ("DRAPE_PROTOCOL_MINOR", num(PROTOCOL_MINOR as f64)),
        ("DRAPE_STATE_MAGIC", magic(drape::wire::state::STATE_MAGIC)),
        ("DRAPE_BUNDLE_MAGIC", magic(drape::wire::bundle::BUNDLE_MAGIC)),
        ("DRAPE_STATE_HEADER_SIZE", num(drape::wire::STATE_HEADER_SIZE as f64)),
        ("DRAPE_BUNDLE_HEADER_SIZE", num(drape::wire::BUNDLE_HEADER_SIZE as f64)),
        ("DRAPE_BUNDLE_ENTRY_SIZE", num(layout::entry::SIZE as f64)),
        ("DRAPE_BUNDLE_ALIGN", num(layout::BUNDLE_ALIGN as f64)),
        ("DRAPE_ENCODING_FLOAT32", num(Encoding::Float32 as u8 as f64)),
        ("DRAPE_ENCODING_FLOAT16", num(Encoding::Float16 as u8 as f64)),
        ("DRAPE_ENCODING_QUANT16", num(Encoding::Quant16 as u8 as f64)),
        // 1.5: the predictive encoding, which this crate does not decode yet (PROTOCOL.md 9.2)
        ("DRAPE_ENCODING_PREDICTIVE", num(3.0)),
        ("DRAPE_FLAG_NORMALS", num(FLAG_NORMALS as f64)),
        ("DRAPE_FLAG_RESET", num(FLAG_RESET as f64)),
        ("DRAPE_QUANT16_MAX", num(half::QUANT_MAX)),
        ("DRAPE_SNORM16_MAX", num(half::SNORM_MAX)),
        ("DRAPE_FLOAT16_MAX", num(half::FLOAT16_MAX as f64)),
    ])
}

#[test]
fn layouts_and_constants_match_drape_wire_h() {
    let path = header_path();
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    let (structs, defines) = parse_header(&text);
    assert_eq!(structs.len(), 3, "structs of drape_wire.h: {structs:?}");

    let mut c = String::from("#include <stddef.h>\n#include <stdio.h>\n#include \"drape_wire.h\"\nint main(void) {\n");
    for (name, fields) in &structs {
        c += &format!("    printf(\"size {name} %zu\\n\", sizeof({name}));\n");
        for f in fields {
            c += &format!("    printf(\"field {name} {f} %zu %zu\\n\", offsetof({name}, {f}), sizeof((({name} *)0)->{f}));\n");
        }
    }
    for (name, value) in &defines {
        if name == "DRAPE_WIRE_H" {
            continue;
        }
        if value.starts_with('"') {
            c += &format!("    printf(\"define {name} %s\\n\", {name});\n");
        } else {
            // every number as a double: integers and the float16 maximum alike
            c += &format!("    printf(\"define {name} %f\\n\", (double)({name}));\n");
        }
    }
    c += "    return 0;\n}\n";
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("layout");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("layout.c"), &c).unwrap();
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let exe = dir.join("layout");
    let out = Command::new(&cc)
        .args(["-std=c11", "-Wall", "-Werror", "-I"])
        .arg(path.parent().unwrap())
        .arg(dir.join("layout.c"))
        .arg("-o")
        .arg(&exe)
        .output()
        .unwrap_or_else(|e| panic!("cannot run the C compiler {cc:?} (needed to check drape_wire.h): {e}"));
    assert!(out.status.success(), "{cc} failed on the generated layout.c:\n{}\n{c}", String::from_utf8_lossy(&out.stderr));
    let run = Command::new(&exe).output().unwrap();
    assert!(run.status.success());
    let printed = String::from_utf8(run.stdout).unwrap();

    let mut c_fields: BTreeMap<String, Vec<Field>> = BTreeMap::new();
    let mut c_sizes = BTreeMap::new();
    let mut c_defines = BTreeMap::new();
    for line in printed.lines() {
        let w: Vec<&str> = line.split(' ').collect();
        match w[0] {
            "size" => {
                c_sizes.insert(w[1].to_string(), w[2].parse::<usize>().unwrap());
            }
            "field" => c_fields.entry(w[1].to_string()).or_default().push(Field {
                name: Box::leak(w[2].to_string().into_boxed_str()),
                offset: w[3].parse().unwrap(),
                size: w[4].parse().unwrap(),
            }),
            "define" => {
                c_defines.insert(w[1].to_string(), w[2..].join(" "));
            }
            _ => unreachable!("{line}"),
        }
    }
    for (name, _) in &structs {
        let (fields, size) = rust_layout(name);
        assert_eq!(c_fields[name], fields, "{name}: fields (name, offset, size) in drape_wire.h vs drape::wire::layout");
        assert_eq!(c_sizes[name], size, "{name}: sizeof");
        let end = fields.last().map_or(0, |f| f.offset + f.size);
        assert_eq!(end, size, "{name}: the fields cover the struct");
    }
    let rust = rust_constants();
    for (name, value) in &c_defines {
        let mine = rust.get(name.as_str()).unwrap_or_else(|| panic!("drape_wire.h defines {name} = {value}, unknown to this test"));
        if name == "DRAPE_PROTOCOL_MINOR" {
            // the crate may speak an older minor than the header's (it reads every minor of the major)
            assert!(mine.parse::<f64>().unwrap() <= value.parse::<f64>().unwrap(), "{name}: the crate's {mine} is newer than drape_wire.h's {value}");
        } else {
            assert_eq!(mine, value, "{name}");
        }
    }
    assert_eq!(c_defines.len(), rust.len(), "constants of drape_wire.h: {c_defines:?}");
}
