//! A bandwidth limit for testing players on a slow or changing link over loopback (`msth serve
//! --rate-limit`): every response body is paced to a rate in bytes per second, which may follow
//! a schedule of changes over the server's lifetime.
//!
//! The rate applies per response (a connection carries one response at a time, so per
//! connection too). Bodies are cut into pieces of at most 50 ms at the current rate; each piece
//! waits until the bytes before it would have been sent at the rate, so a response never runs
//! ahead of the rate (it may fall behind it when the client reads slowly).

use std::time::{Duration, Instant};

use axum::body::{Body, Bytes};
use futures_util::StreamExt;

/// A rate in bytes per second from `--rate-limit`'s text: a number with an optional unit,
/// `k`/`M`/`G` (thousands, millions, billions of bytes) or `kbit`/`mbit`/`gbit` (of bits):
/// `125000`, `1.25M`, `10mbit`.
pub fn parse_rate(text: &str) -> Result<f64, String> {
    let t = text.trim();
    let lower = t.to_ascii_lowercase();
    let (number, scale) = [
        ("gbit", 1e9 / 8.0),
        ("mbit", 1e6 / 8.0),
        ("kbit", 1e3 / 8.0),
        ("g", 1e9),
        ("m", 1e6),
        ("k", 1e3),
    ]
    .iter()
    .find_map(|(unit, scale)| lower.strip_suffix(unit).map(|n| (n.to_string(), *scale)))
    .unwrap_or((lower.clone(), 1.0));
    let value: f64 = number
        .trim()
        .parse()
        .map_err(|_| format!("{t:?}: not a rate (e.g. 125000, 1.25M, 10mbit)"))?;
    let rate = value * scale;
    if !(rate.is_finite() && rate >= 1.0) {
        return Err(format!("{t:?}: a rate must be at least 1 byte/s"));
    }
    Ok(rate)
}

/// Rates over time: `(seconds since the server started, bytes per second)`, by time, the first
/// at 0.
#[derive(Debug, Clone, PartialEq)]
pub struct RateSchedule {
    steps: Vec<(f64, f64)>,
}

impl RateSchedule {
    /// A constant rate.
    pub fn constant(bytes_per_second: f64) -> Self {
        RateSchedule {
            steps: vec![(0.0, bytes_per_second)],
        }
    }

    /// Parses `RATE[,RATE@SECONDS]...`: the first rate from the start, each next one from its
    /// time (seconds since the server started, increasing): `50mbit,3mbit@5,50mbit@10`.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut steps = Vec::new();
        for (i, part) in text.split(',').enumerate() {
            let (rate, at) = match part.split_once('@') {
                Some((r, s)) if i > 0 => {
                    let s: f64 =
                        s.trim().trim_end_matches('s').parse().map_err(|_| {
                            format!("{part:?}: RATE@SECONDS wants a time in seconds")
                        })?;
                    (r, s)
                }
                Some(_) => {
                    return Err(format!(
                        "{part:?}: the first rate holds from the start (no @)"
                    ))
                }
                None if i == 0 => (part, 0.0),
                None => return Err(format!("{part:?}: a later rate needs @SECONDS")),
            };
            let rate = parse_rate(rate)?;
            if let Some(&(prev, _)) = steps.last() {
                if !(at.is_finite() && at > prev) {
                    return Err(format!("{part:?}: times must increase"));
                }
            }
            steps.push((at, rate));
        }
        Ok(RateSchedule { steps })
    }

    /// The rate at `seconds` since the start.
    pub fn rate_at(&self, seconds: f64) -> f64 {
        self.steps
            .iter()
            .rev()
            .find(|(at, _)| seconds >= *at)
            .map_or(self.steps[0].1, |&(_, r)| r)
    }
}

/// `body` paced by `schedule`, whose time counts from `start`.
pub(crate) fn throttle(body: Body, schedule: std::sync::Arc<RateSchedule>, start: Instant) -> Body {
    struct State {
        inner: axum::body::BodyDataStream,
        pending: Bytes,
        /// When the bytes sent so far may all have left, at the rates they were sent at.
        due: Option<Instant>,
        schedule: std::sync::Arc<RateSchedule>,
        start: Instant,
    }
    let state = State {
        inner: body.into_data_stream(),
        pending: Bytes::new(),
        due: None,
        schedule,
        start,
    };
    let stream = futures_util::stream::unfold(state, |mut st| async move {
        if st.pending.is_empty() {
            match st.inner.next().await? {
                Ok(b) => st.pending = b,
                Err(e) => return Some((Err(std::io::Error::other(e)), st)),
            }
        }
        let now = Instant::now();
        let rate = st
            .schedule
            .rate_at(now.duration_since(st.start).as_secs_f64());
        // At most 50 ms of bytes at the current rate in one piece.
        let most = ((rate * 0.05) as usize).max(1);
        let piece = st.pending.split_to(most.min(st.pending.len()));
        let due = st.due.map_or(now, |d| d.max(now));
        tokio::time::sleep_until(due.into()).await;
        st.due = Some(due + Duration::from_secs_f64(piece.len() as f64 / rate));
        Some((Ok::<Bytes, std::io::Error>(piece), st))
    });
    Body::from_stream(stream)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_parse_with_units_and_refuse_nonsense() {
        assert_eq!(parse_rate("125000").unwrap(), 125000.0);
        assert_eq!(parse_rate("1.25M").unwrap(), 1.25e6);
        assert_eq!(parse_rate("10mbit").unwrap(), 1.25e6);
        assert_eq!(parse_rate("2Mbit").unwrap(), 250000.0);
        assert_eq!(parse_rate("8kbit").unwrap(), 1000.0);
        for bad in ["", "fast", "-5", "0", "nan", "inf", "0.5"] {
            assert!(parse_rate(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn schedules_step_at_their_times() {
        let s = RateSchedule::parse("50mbit,3mbit@5,50mbit@10s").unwrap();
        assert_eq!(s.rate_at(0.0), 6.25e6);
        assert_eq!(s.rate_at(4.9), 6.25e6);
        assert_eq!(s.rate_at(5.0), 375000.0);
        assert_eq!(s.rate_at(9.99), 375000.0);
        assert_eq!(s.rate_at(60.0), 6.25e6);
        assert_eq!(
            RateSchedule::parse("1M").unwrap(),
            RateSchedule::constant(1e6)
        );
        for bad in ["1M@2", "1M,2M", "1M,2M@5,3M@5", "1M,2M@x", "1M,,2M@3"] {
            assert!(RateSchedule::parse(bad).is_err(), "{bad:?}");
        }
    }
}
