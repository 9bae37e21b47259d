//! Mesh colliders (protocol 1.8, PROTOCOL.md 5.4) against a real `drape serve` on loopback
//! (tests/common): a cape dropped on a small closed mesh (a 0.4 m box sent with its submission)
//! keeps every vertex outside it in every state received, also after the box is moved rigidly
//! by a pose (also as a batch item) and re-posed by new vertices, while without the mesh the cape falls through the
//! box; the scene request (1.7) sets and moves a scene's mesh, from its owner only; bad meshes
//! are refused before sending (the triangle named) and changes of no mesh by the server.
mod common;

use drape::client::{Client, Cloth};
use drape::wire::{Control, ErrorCode, Grid, MeshCollider, Orientation, SceneRequest, Shape, Submit};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn shared() -> Option<&'static common::Server> {
    static S: OnceLock<Option<common::Server>> = OnceLock::new();
    S.get_or_init(|| common::drape_bin().map(|b| common::start(&b, &[]))).as_ref()
}

const HALF: f32 = 0.2; // the box's half extent, metres
const COLS: u32 = 9;
const N: usize = 3 * (COLS * COLS) as usize;
const IDENTITY: [f64; 4] = [1.0, 0.0, 0.0, 0.0];

/// A closed box of half extent `half` about the origin: 8 vertices, 12 triangles each turned
/// counter-clockwise seen from outside (its normal away from the centre).
fn box_mesh(half: f32) -> (Vec<f32>, Vec<u32>) {
    let v: Vec<f32> = (0..8).flat_map(|i| [(i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32].map(|c| (2.0 * c - 1.0) * half)).collect();
    // each face: the 4 corners with one axis fixed, as two triangles
    let mut t = Vec::new();
    for axis in 0..3 {
        for side in 0..2u32 {
            let corners: Vec<u32> = (0..8u32).filter(|i| (i >> axis) & 1 == side).collect();
            for tri in [[corners[0], corners[1], corners[3]], [corners[0], corners[3], corners[2]]] {
                let p = |i: u32| [v[3 * i as usize], v[3 * i as usize + 1], v[3 * i as usize + 2]];
                let (a, b, c) = (p(tri[0]), p(tri[1]), p(tri[2]));
                let (u, w) = ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
                let n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]];
                let centroid = [(a[0] + b[0] + c[0]) / 3.0, (a[1] + b[1] + c[1]) / 3.0, (a[2] + b[2] + c[2]) / 3.0];
                let outward = n[0] * centroid[0] + n[1] * centroid[1] + n[2] * centroid[2] > 0.0;
                t.extend(if outward { tri } else { [tri[0], tri[2], tri[1]] });
            }
        }
    }
    (v, t)
}

/// Vertices strictly inside the box of half extent `half` centred at `centre` (1 mm in).
fn inside(pos: &[f32], centre: [f64; 3], half: f32) -> usize {
    pos.chunks_exact(3)
        .filter(|p| (0..3).all(|k| ((p[k] as f64 - centre[k]).abs() as f32) < half - 1e-3))
        .count()
}

/// A 0.6 m cape 0.3 m above the box top (centred over it), with the box as its mesh at `centre`.
fn drop_cape(client: &Client, centre: [f64; 3], with_mesh: bool) -> Cloth {
    let top = centre[1] + HALF as f64;
    let g = Grid { cols: COLS, rows: COLS, width: 0.6, height: 0.6, orientation: Orientation::Horizontal,
                   origin: [centre[0] - 0.3, top + 0.3, centre[2] - 0.3] };
    let mut sub = Submit { substeps: Some(2), ..Submit::new("", Shape::Grid(g.clone())) };
    sub.material.thickness = Some(0.02);
    sub.material.friction = Some(0.3);
    if with_mesh {
        let (v, t) = box_mesh(HALF);
        sub.mesh_collider = Some(MeshCollider::mesh(v, t).at(centre, IDENTITY));
    }
    client.submit_grid(g, sub).unwrap()
}

/// The next `states` states with a tick from `from` on (counted: as many ticks of simulated time
/// at least, whatever the machine's pace; a deadline of `common::WAIT`): the most vertices
/// inside the box at `centre` in any of them, their count and the lowest y of the last one.
fn watch(cloth: &Cloth, states: usize, from: u64, centre: [f64; 3]) -> (usize, usize, f32) {
    let mut pos = vec![0f32; N];
    let (mut worst, mut n, mut low) = (0, 0, f32::MAX);
    let t0 = Instant::now();
    while n < states {
        assert!(t0.elapsed() < common::WAIT, "{n} of {states} states");
        if let Some(st) = cloth.wait_state(&mut pos, None, Duration::from_millis(100)).unwrap() {
            if st.tick >= from {
                worst = worst.max(inside(&pos, centre, HALF));
                n += 1;
                low = pos.chunks_exact(3).map(|p| p[1]).fold(f32::MAX, f32::min);
            }
        }
    }
    (worst, n, low)
}

#[test]
fn a_cape_dropped_on_a_mesh_stays_outside_it() {
    let Some(server) = shared() else { return };
    let client = common::connect(&[server], Some(&server.id), false);
    let centre = [0.0, 1.0, 0.0];
    let cape = drop_cape(&client, centre, true);
    let (worst, _, low) = watch(&cape, 90, 0, centre);
    assert_eq!(worst, 0, "vertices inside the box");
    assert!(low > 0.5 && low < 1.2 + 0.3, "held up by the box, lowest y {low}");
    // the per-tick rigid move: 5 cm sideways
    let moved = [0.05, 1.0, 0.0];
    let tick = cape.move_mesh_collider(moved, IDENTITY, true).unwrap().unwrap();
    let (worst, n, _) = watch(&cape, 36, tick, moved);
    assert!(worst == 0, "{worst} vertices inside the moved box ({n} states)");
    // the same move as a batch item (one request for many cloths' meshes)
    let mut batch = client.batch();
    batch.add(&cape, Control { mesh_collider: Some(MeshCollider::pose(moved, IDENTITY)), ..Default::default() });
    let items = client.send_batch_applied(batch).unwrap();
    assert!(items.len() == 1 && items[0].is_ok(), "{items:?}");
    // a re-pose: the same box's vertices, 2 cm taller, at the moved pose
    let (mut v, _) = box_mesh(HALF);
    v.iter_mut().skip(1).step_by(3).for_each(|y| *y *= 1.1);
    let tick = cape.set_mesh_collider(MeshCollider::repose(v).at(moved, IDENTITY), true).unwrap().unwrap();
    let (worst, _, _) = watch(&cape, 24, tick, moved);
    assert_eq!(worst, 0, "vertices inside the re-posed box");
    // the server refuses a re-pose of another vertex count; then the mesh is removed
    let e = cape.set_mesh_collider(MeshCollider::repose(vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]), true).unwrap_err();
    assert_eq!(e.code, ErrorCode::InvalidValue, "{e}");
    cape.set_mesh_collider(MeshCollider::removal(), true).unwrap();
    let e = cape.move_mesh_collider(moved, IDENTITY, true).unwrap_err();
    assert_eq!(e.code, ErrorCode::InvalidValue, "a move of no mesh: {e}");
    cape.remove().unwrap();
    // without the mesh the same cape falls through the box
    let bare = drop_cape(&client, centre, false);
    let (worst, _, _) = watch(&bare, 72, 0, centre);
    assert!(worst > 0, "without the mesh no vertex ever entered the box: the check checks nothing");
    bare.remove().unwrap();
    client.close(true);
}

#[test]
fn bad_meshes_are_refused_before_sending() {
    let Some(server) = shared() else { return };
    let client = common::connect(&[server], Some(&server.id), false);
    let (v, mut t) = box_mesh(HALF);
    t[7] = t[6]; // triangle 2 repeats a vertex
    let g = Grid::new(4, 4);
    let sub = Submit { mesh_collider: Some(MeshCollider::mesh(v.clone(), t)), ..Submit::new("", Shape::Grid(g.clone())) };
    let e = client.submit_grid(g.clone(), sub).unwrap_err();
    assert!(e.code == ErrorCode::InvalidValue && e.message.contains("triangle 2"), "{e}");
    let cape = client.submit_grid(g.clone(), Submit::new("", Shape::Grid(g.clone()))).unwrap();
    let e = cape.move_mesh_collider([0.0; 3], [0.0; 4], true).unwrap_err();
    assert!(e.code == ErrorCode::InvalidValue && e.message.contains("rotation"), "{e}");
    let e = cape.move_mesh_collider([0.0; 3], IDENTITY, true).unwrap_err(); // the server: no mesh to move
    assert_eq!(e.code, ErrorCode::InvalidValue, "{e}");
    client.close(true);
    // placed by load (no server id): a 1.8 server takes a cloth with its own mesh
    let placed = common::connect(&[server], None, false);
    let (v, t) = box_mesh(HALF);
    let sub = Submit { mesh_collider: Some(MeshCollider::mesh(v, t)), ..Submit::new("", Shape::Grid(g.clone())) };
    let cape = placed.submit_grid(g, sub).unwrap();
    assert_eq!(cape.server(), server.id);
    placed.close(true);
}

#[test]
fn a_scenes_mesh_is_set_and_moved_by_its_owner_only() {
    let Some(server) = shared() else { return };
    let owner = common::connect(&[server], Some(&server.id), false);
    let g = Grid::new(4, 4);
    let scene = format!("rs-mesh-{}", std::process::id());
    let cape = owner.submit_grid(g.clone(), Submit { scene: Some(scene.clone()), ..Submit::new("", Shape::Grid(g)) }).unwrap();
    let (v, t) = box_mesh(HALF);
    let req = SceneRequest { mesh_collider: Some(MeshCollider::mesh(v, t).at([0.0, 0.5, 0.0], IDENTITY)), ..SceneRequest::new("", &scene) };
    let rep = owner.set_scene(req, None).unwrap();
    assert_eq!((rep.owner.as_str(), rep.cloths), (owner.client_id(), 1));
    let moved = owner.move_scene_mesh(&scene, [0.1, 0.5, 0.0], IDENTITY, None).unwrap();
    assert!(moved.tick >= rep.tick);
    let stranger = common::connect(&[server], Some(&server.id), false);
    let e = stranger.move_scene_mesh(&scene, [0.2, 0.5, 0.0], IDENTITY, None).unwrap_err();
    assert_eq!(e.code, ErrorCode::Forbidden, "{e}");
    cape.remove().unwrap();
    stranger.close(true);
    owner.close(true);
}

/// The C ABI: a grid submitted with `drape_submit_grid_ex` into a scene of its own with a mesh
/// and a thickness; its mesh moved in a batch; the scene's mesh set and moved by its owner (this
/// C client: its cloth founded the scene); a zero quaternion refused before sending.
#[test]
fn c_abi_meshes_and_scene() {
    use drape::ffi::*;
    use std::ffi::CString;
    let Some(s) = shared() else { return };
    let scene = CString::new(format!("rs-c-{}", std::process::id())).unwrap();
    let (v, t) = box_mesh(HALF);
    unsafe {
        let client = common::c_open(s, None);
        let mesh = DrapeMeshCollider {
            vertices: v.as_ptr(), vertex_count: 8, triangles: t.as_ptr(), triangle_count: 12,
            position: [0.0, 1.0, 0.0], rotation: [0.0; 4], remove: false,
        };
        let extras = DrapeSubmitExtras { thickness: 0.02, contact_stiffness: 0.0, scene: scene.as_ptr(), mesh_collider: &mesh };
        let grid = DrapeGrid { cols: 4, rows: 4, width: 0.0, height: 0.0, vertical: false, origin: [0.0, 2.0, 0.0] };
        let copts = common::c_cloth_options(&[], false);
        let mut cloth = std::ptr::null_mut();
        assert_eq!(drape_submit_grid_ex(client, &grid, &copts, &extras, &mut cloth), DRAPE_OK);
        let pose = DrapeMeshCollider { vertices: std::ptr::null(), triangles: std::ptr::null(), vertex_count: 0, triangle_count: 0,
                                       position: [0.1, 1.0, 0.0], rotation: [1.0, 0.0, 0.0, 0.0], remove: false };
        let batch = drape_batch_new();
        assert_eq!(drape_batch_set_mesh_collider(batch, cloth, &pose), DRAPE_OK);
        let (mut codes, mut ticks) = ([-1i32; 1], [0u64; 1]);
        assert_eq!(drape_batch_send(client, batch, true, codes.as_mut_ptr(), ticks.as_mut_ptr(), 1), DRAPE_OK);
        assert_eq!(codes[0], DRAPE_OK);
        drape_batch_free(batch);
        let mut tick = 0u64;
        assert_eq!(drape_client_set_scene_mesh_collider(client, scene.as_ptr(), &mesh, std::ptr::null(), &mut tick), DRAPE_OK);
        assert!(tick > 0);
        assert_eq!(drape_client_set_scene_mesh_collider(client, scene.as_ptr(), &pose, std::ptr::null(), &mut tick), DRAPE_OK);
        let zero = [0.0f64; 4];
        assert_eq!(drape_cloth_move_mesh_collider(cloth, pose.position.as_ptr(), zero.as_ptr(), true, &mut tick), DRAPE_E_INVALID_VALUE);
        let removal = DrapeMeshCollider { remove: true, ..pose };
        assert_eq!(drape_cloth_set_mesh_collider(cloth, &removal, true, &mut tick), DRAPE_OK);
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
    }
}
