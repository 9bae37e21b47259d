//! Rates per subscriber (protocol 1.8, 1.9's lower rates; PROTOCOL.md 9.3), no network: the
//! decimated keys (`{state or bundle key}/every/{k}`, k in [`RATES`]), which rates a server of a
//! version serves ([`served_rates`]) and [`Governor`], `rate = auto`'s rule, stepping along the
//! ladder of the rates its subscription's server serves,
//! the Python SDK's `client/rates.py` `RateGovernor` step for step: over each window of receive
//! time it looks at the 90th percentile of its states' lateness (`receive - server` time minus
//! the smallest such difference over the last windows: the clock offset and the link's own delay
//! are not lateness) and at the share of the window's states that never came; either over its
//! bound steps one rate down, or straight to the lowest when the lateness passes `jump_s`. A
//! step up waits `quiet_s` of good windows, doubled (up to `max_quiet_s`) each time a step up
//! is followed by a step down within three windows. The window after a change is not judged.
//! The numbers are [`GovernorConfig::default`]; `tests/vectors/rates.json` holds the Python
//! governor's and traces of its decisions, which `tests/rates.rs` replays against this one.
use std::collections::VecDeque;

/// The rates a subscriber may take a key at, each with the first protocol version whose servers
/// serve it: every k-th state (1: the key itself; 1.8: 2 and 3, 30 and 20 Hz at the default 60 Hz
/// tick; 1.9: 6 and 12, 10 and 5 Hz). The Python SDK's `protocol.RATE_SINCE`.
pub const RATE_SINCE: [(u8, (u8, u8)); 5] = [(1, (1, 0)), (2, (1, 8)), (3, (1, 8)), (6, (1, 9)), (12, (1, 9))];

/// The rates of [`RATE_SINCE`], in order.
pub const RATES: [u8; RATE_SINCE.len()] = {
    let mut out = [0u8; RATE_SINCE.len()];
    let mut i = 0;
    while i < out.len() {
        out[i] = RATE_SINCE[i].0;
        i += 1;
    }
    out
};

/// The rates a server of protocol `version` serves (None: unknown, the full rate only): a cloth
/// on a 1.7 server stays on the full-rate key, on a 1.8 one takes at most every 3rd state.
pub fn served_rates(version: Option<(u8, u8)>) -> Vec<u8> {
    match version {
        None => vec![1],
        Some(v) => RATE_SINCE.iter().filter(|(_, since)| v >= *since).map(|(k, _)| *k).collect(),
    }
}

/// The rate a subscription asking for every `k`-th state takes from a server serving `served`:
/// `k` itself, or the served rate nearest below it (a 1.8 server asked for 6 or 12: every 3rd).
pub fn fit_rate(k: u8, served: &[u8]) -> u8 {
    served.iter().copied().filter(|&r| r <= k).max().unwrap_or(1)
}

/// The key of every `every`-th state of a state or bundle key (`every` = 1: `key` itself);
/// None for a rate not in [`RATES`].
pub fn every_key(key: &str, every: u8) -> Option<String> {
    match every {
        1 => Some(key.to_string()),
        k if RATES.contains(&k) => Some(format!("{key}/every/{k}")),
        _ => None,
    }
}

/// (the full-rate key, k) of a decimated key; (`key`, 1) for any other key.
pub fn split_every(key: &str) -> (&str, u8) {
    if let Some((base, k)) = key.rsplit_once("/every/") {
        if let Ok(k) = k.parse::<u8>() {
            if k != 1 && RATES.contains(&k) {
                return (base, k);
            }
        }
    }
    (key, 1)
}

/// A subscription's rate: every k-th state (k in [`RATES`]), or `Auto`: the full rate, stepped
/// down by a [`Governor`] when states arrive late.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Rate {
    #[default]
    Full,
    Every(u8),
    Auto,
}

impl Rate {
    /// The rate of `k` (one of [`RATES`]), or `Auto` for 0 (the C ABI's `DRAPE_RATE_AUTO`); None otherwise.
    pub fn from_k(k: u32) -> Option<Rate> {
        match k {
            0 => Some(Rate::Auto),
            1 => Some(Rate::Full),
            _ => u8::try_from(k).ok().filter(|k| RATES.contains(k)).map(Rate::Every),
        }
    }
    /// (the k to start at, whether a governor steps it).
    pub fn start(self) -> (u8, bool) {
        match self {
            Rate::Full => (1, false),
            Rate::Every(k) => (k, false),
            Rate::Auto => (1, true),
        }
    }
}

/// The governor's numbers (the Python SDK's `RateGovernor` defaults; checked against
/// `tests/vectors/rates.json`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GovernorConfig {
    /// Length of a window of receive time, seconds.
    pub window_s: f64,
    /// Lateness (the window's `late_percentile`) past which it steps down, seconds.
    pub late_s: f64,
    /// Lateness past which it steps straight to the lowest rate, seconds.
    pub jump_s: f64,
    /// Share of a window's states that never came past which it steps down.
    pub lost_share: f64,
    /// Good windows' length before a step up, seconds (doubled after a step up that did not hold).
    pub quiet_s: f64,
    pub max_quiet_s: f64,
    /// Windows the lateness baseline (the smallest difference) is kept over.
    pub baseline_windows: usize,
    pub late_percentile: f64,
    /// Windows after a change that are not judged (what was queued before it drains).
    pub settle_windows: f64,
    /// A step down within this many windows of a step up doubles the quiet period.
    pub failed_up_windows: f64,
}

impl Default for GovernorConfig {
    fn default() -> Self {
        GovernorConfig {
            window_s: 1.0,
            late_s: 0.05,
            jump_s: 0.2,
            lost_share: 0.25,
            quiet_s: 5.0,
            max_quiet_s: 60.0,
            baseline_windows: 30,
            late_percentile: 90.0,
            settle_windows: 1.5,
            failed_up_windows: 3.0,
        }
    }
}

/// Steps one subscription's rate down when its states arrive late, up after a quiet period.
/// Every input is an argument (the receive time included): tests drive it with injected times.
#[derive(Debug, Clone)]
pub struct Governor {
    pub cfg: GovernorConfig,
    /// The rate it holds now.
    pub rate: u8,
    /// The ladder it steps along: the rates its subscription's server serves ([`served_rates`]).
    pub rates: Vec<u8>,
    pub step_downs: u64,
    pub step_ups: u64,
    /// The quiet period now (seconds).
    pub quiet_s: f64,
    start: Option<u64>,
    first_tick: u64,
    last_tick: u64,
    diffs: Vec<i64>,
    mins: VecDeque<i64>,
    settle_until: u64,
    good_since: Option<u64>,
    up_at: Option<u64>,
}

impl Governor {
    pub fn new(rate: u8) -> Governor {
        Governor::with(GovernorConfig::default(), rate)
    }

    pub fn with(cfg: GovernorConfig, rate: u8) -> Governor {
        Governor {
            cfg,
            rate,
            rates: RATES.to_vec(),
            step_downs: 0,
            step_ups: 0,
            quiet_s: cfg.quiet_s,
            start: None,
            first_tick: 0,
            last_tick: 0,
            diffs: Vec::new(),
            mins: VecDeque::new(),
            settle_until: 0,
            good_since: None,
            up_at: None,
        }
    }

    /// The ladder of the rates the subscription's server serves (placed, or failed over, on a 1.8
    /// server: it stops at 3); the rate it holds now ([`fit_rate`]: its own or the one below).
    pub fn limit(&mut self, rates: &[u8]) -> u8 {
        self.rates = rates.to_vec();
        self.rate = fit_rate(self.rate, rates);
        self.rate
    }

    /// The subscription was switched to `rate` by hand: judged from there (the next window
    /// is not judged).
    pub fn set_rate(&mut self, rate: u8, now_ns: u64) {
        if rate != self.rate {
            self.change(rate, now_ns);
        }
    }

    /// A state (or bundle) of `tick` stamped `server_ns` by the server arrived at `receive_ns`
    /// (ns, the client's clock); the new rate when this changes it, else None.
    pub fn observe(&mut self, tick: u64, server_ns: u64, receive_ns: u64) -> Option<u8> {
        if server_ns == 0 || receive_ns == 0 {
            return None;
        }
        let start = *self.start.get_or_insert_with(|| {
            self.first_tick = tick;
            self.diffs.clear();
            receive_ns
        });
        self.diffs.push(receive_ns as i64 - server_ns as i64);
        self.last_tick = self.last_tick.max(tick);
        if ((receive_ns as i64 - start as i64) as f64) < self.cfg.window_s * 1e9 {
            return None;
        }
        self.judge(receive_ns)
    }

    fn judge(&mut self, now: u64) -> Option<u8> {
        let min = *self.diffs.iter().min()?;
        if self.mins.len() == self.cfg.baseline_windows.max(1) {
            self.mins.pop_front();
        }
        self.mins.push_back(min);
        let base = *self.mins.iter().min()?;
        let expected = (self.last_tick.saturating_sub(self.first_tick) / self.rate as u64 + 1) as f64;
        let lost = 1.0 - (self.diffs.len() as f64).min(expected) / expected.max(1.0);
        let mut late: Vec<f64> = self.diffs.iter().map(|d| (d - base) as f64).collect();
        let late = percentile(&mut late, self.cfg.late_percentile) / 1e9;
        self.start = None;
        self.last_tick = 0;
        if now < self.settle_until {
            return None;
        }
        let rates = &self.rates;
        let i = rates.iter().position(|&r| r == self.rate).unwrap_or(0);
        if late > self.cfg.late_s || lost > self.cfg.lost_share {
            self.good_since = None;
            if i + 1 >= rates.len() {
                return None;
            }
            if self.up_at.is_some_and(|u| (now as f64 - u as f64) <= self.cfg.failed_up_windows * self.cfg.window_s * 1e9) {
                self.quiet_s = (2.0 * self.quiet_s).min(self.cfg.max_quiet_s); // the step up did not hold
            }
            self.up_at = None;
            self.step_downs += 1;
            let to = if late > self.cfg.jump_s { rates[rates.len() - 1] } else { rates[i + 1] };
            return Some(self.change(to, now));
        }
        let since = *self.good_since.get_or_insert(now);
        if i > 0 && (now - since) as f64 >= self.quiet_s * 1e9 {
            self.step_ups += 1;
            self.up_at = Some(now);
            self.good_since = None;
            return Some(self.change(self.rates[i - 1], now));
        }
        None
    }

    fn change(&mut self, rate: u8, now: u64) -> u8 {
        self.rate = rate;
        self.settle_until = now + (self.cfg.settle_windows * self.cfg.window_s * 1e9) as u64;
        rate
    }
}

/// numpy's default (linear) percentile `q` of `v` (not empty; sorted in place).
fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let pos = (v.len() - 1) as f64 * (q / 100.0); // numpy: (n - 1) * quantile
    let (lo, t) = (pos.floor() as usize, pos - pos.floor());
    let (a, b) = (v[lo], v[(lo + 1).min(v.len() - 1)]);
    // numpy's _lerp: a + (b - a) t, from the far end when t >= 0.5
    if t >= 0.5 {
        b - (b - a) * (1.0 - t)
    } else {
        a + (b - a) * t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys() {
        assert_eq!(every_key("drape/client/a/states", 2).unwrap(), "drape/client/a/states/every/2");
        assert_eq!(every_key("k", 1).unwrap(), "k");
        assert_eq!(every_key("k", 4), None);
        assert_eq!(split_every("drape/cloth/x/state/every/3"), ("drape/cloth/x/state", 3));
        assert_eq!(split_every("drape/cloth/x/state/every/9"), ("drape/cloth/x/state/every/9", 1));
        assert_eq!(every_key("k", 12).unwrap(), "k/every/12");
        assert_eq!(split_every("drape/cloth/x/state/every/6"), ("drape/cloth/x/state", 6));
        assert_eq!(RATES, [1, 2, 3, 6, 12]);
        assert_eq!(served_rates(Some((1, 8))), [1, 2, 3]);
        assert_eq!(served_rates(Some((1, 9))), RATES);
        assert_eq!(served_rates(Some((2, 0))), RATES);
        assert_eq!(served_rates(Some((1, 7))), [1]);
        assert_eq!(served_rates(None), [1]);
        assert_eq!((fit_rate(12, &[1, 2, 3]), fit_rate(6, &RATES), fit_rate(3, &[1])), (3, 6, 1));
        assert_eq!(Rate::from_k(0), Some(Rate::Auto));
        assert_eq!(Rate::from_k(3).map(Rate::start), Some((3, false)));
        assert_eq!(Rate::from_k(12).map(Rate::start), Some((12, false)));
        assert_eq!(Rate::from_k(4), None);
        assert_eq!(Rate::from_k(268), None);
        let mut g = Governor::new(12);
        assert_eq!((g.limit(&served_rates(Some((1, 8)))), g.rates.as_slice()), (3, &[1u8, 2, 3][..]));
    }

    #[test]
    fn percentile_is_numpys() {
        // np.percentile([1, 2, 3, 4, 10], 90) == 7.6; of [5], 5
        assert!((percentile(&mut [10.0, 1.0, 3.0, 2.0, 4.0], 90.0) - 7.6).abs() < 1e-12);
        assert_eq!(percentile(&mut [5.0], 90.0), 5.0);
    }
}
