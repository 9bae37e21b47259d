//! Comparing a cloth's states with a float32 twin's (the same cloth submitted with
//! `float32`): states read by age (tick - first tick), and the largest coordinate difference
//! between states of the same age. The live tests of coded streams (predictive, decimated) use it.
use drape::client::Cloth;
use drape::wire::Encoding;
use std::collections::BTreeMap;
use super::WAIT;
use std::time::{Duration, Instant};

/// States by age (tick - the cloth's first tick): the state's tick and its positions.
pub type ByAge = BTreeMap<u64, (u64, Vec<f32>)>;

/// States read from `cloth` into `out` by age until it holds age `age` or a later one (the twin
/// read as far as the states it is compared with: counted, whatever the machine's pace; panics
/// after [`WAIT`] without it); their encodings, in order. A state shown is never garbage.
pub fn read_to_age(cloth: &Cloth, age: u64, out: &mut ByAge) -> Vec<Encoding> {
    let t0 = Instant::now();
    let enc = read_while(cloth, out, |got| last_age(got).is_none_or(|a| a < age) && t0.elapsed() < WAIT);
    assert!(last_age(out).is_some_and(|a| a >= age), "no state of age {age} or later in {WAIT:?}");
    enc
}

/// The newest (largest) age held (None: no state).
pub fn last_age(states: &ByAge) -> Option<u64> {
    states.keys().next_back().copied()
}

/// States read from `cloth` into `out` by age until it holds `n` more ages (counted, whatever the
/// machine's pace; panics after [`WAIT`] without them); their encodings, in order.
pub fn read_n_by_age(cloth: &Cloth, n: usize, out: &mut ByAge) -> Vec<Encoding> {
    let (t0, want) = (Instant::now(), out.len() + n);
    let enc = read_while(cloth, out, |got| got.len() < want && t0.elapsed() < WAIT);
    assert!(out.len() >= want, "{} of {n} states in {WAIT:?}", n - (want - out.len()));
    enc
}

/// [`read_n_by_age`] into a new map.
pub fn n_by_age(cloth: &Cloth, n: usize) -> ByAge {
    let mut out = ByAge::new();
    read_n_by_age(cloth, n, &mut out);
    out
}

fn read_while(cloth: &Cloth, out: &mut ByAge, more: impl Fn(&ByAge) -> bool) -> Vec<Encoding> {
    let mut pos = vec![0f32; 3 * cloth.vertex_count() as usize];
    let mut encodings = Vec::new();
    while more(out) {
        if let Some(st) = cloth.wait_state(&mut pos, None, Duration::from_millis(50)).unwrap() {
            assert!(pos.iter().all(|x| x.is_finite()), "a shown state is never garbage");
            out.insert(st.tick - cloth.first_tick(), (st.tick, pos.clone()));
            encodings.push(st.encoding);
        }
    }
    encodings
}

/// [`read_to_age`] into a new map.
pub fn to_age(cloth: &Cloth, age: u64) -> ByAge {
    let mut out = ByAge::new();
    read_to_age(cloth, age, &mut out);
    out
}

/// The largest coordinate difference to the twin's state of the same age, and how many ages
/// matched.
pub fn max_diff(a: &ByAge, twin: &ByAge) -> (f32, usize) {
    let (mut worst, mut n) = (0f32, 0);
    for (age, (_, p)) in a {
        if let Some((_, q)) = twin.get(age) {
            n += 1;
            worst = p.iter().zip(q).map(|(x, y)| (x - y).abs()).fold(worst, f32::max);
        }
    }
    (worst, n)
}
