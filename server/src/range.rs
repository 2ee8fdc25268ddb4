//! RFC 9110 byte ranges and validators, as pure functions over header strings: parsing `Range`
//! (section 14.2), resolving it against a length (14.1.2), `If-Range` (13.1.5), `If-None-Match`
//! (13.1.2) and the strong entity tag this server gives a file. No I/O lives here.
//!
//! Policy: a `Range` that is syntactically invalid, names another unit, or asks for more than one
//! range is ignored and the whole file is sent with 200 (RFC 9110 allows a server to ignore
//! `Range`; this server does not send `multipart/byteranges`).

use std::time::{SystemTime, UNIX_EPOCH};

/// One byte-range spec of a `Range: bytes=...` header; positions are inclusive, as on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ByteRangeSpec {
    /// `bytes=first-last`
    FromTo(u64, u64),
    /// `bytes=first-`
    From(u64),
    /// `bytes=-suffix_len`: the last `suffix_len` bytes.
    Suffix(u64),
}

/// Parses a `Range` header value. `None` means "ignore it and send the full body": invalid
/// syntax, a unit other than `bytes`, or several ranges.
pub fn parse_range(value: &str) -> Option<ByteRangeSpec> {
    let value = value.trim();
    let (unit, set) = value.split_once('=')?;
    if !unit.trim().eq_ignore_ascii_case("bytes") {
        return None;
    }
    let specs: Vec<&str> = set
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .collect();
    let mut parsed = Vec::with_capacity(specs.len().min(2));
    for spec in &specs {
        parsed.push(parse_spec(spec)?);
    }
    match parsed.as_slice() {
        [one] => Some(*one),
        _ => None,
    }
}

fn parse_spec(spec: &str) -> Option<ByteRangeSpec> {
    let (first, last) = spec.split_once('-')?;
    match (first.is_empty(), last.is_empty()) {
        (true, true) => None,
        (true, false) => Some(ByteRangeSpec::Suffix(parse_digits(last)?)),
        (false, true) => Some(ByteRangeSpec::From(parse_digits(first)?)),
        (false, false) => {
            let (a, b) = (parse_digits(first)?, parse_digits(last)?);
            (a <= b).then_some(ByteRangeSpec::FromTo(a, b))
        }
    }
}

/// `1*DIGIT`, saturating at `u64::MAX` (a huge last-pos means "to the end").
fn parse_digits(s: &str) -> Option<u64> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(s.bytes().fold(0u64, |acc, b| {
        acc.saturating_mul(10).saturating_add(u64::from(b - b'0'))
    }))
}

/// Resolves a spec against a representation of `len` bytes: `Some((first, last))` inclusive, or
/// `None` when unsatisfiable (answer 416 with `Content-Range: bytes */len`).
pub fn resolve(spec: ByteRangeSpec, len: u64) -> Option<(u64, u64)> {
    match spec {
        ByteRangeSpec::FromTo(a, b) => (a < len).then(|| (a, b.min(len - 1))),
        ByteRangeSpec::From(a) => (a < len).then(|| (a, len - 1)),
        ByteRangeSpec::Suffix(n) => (n > 0 && len > 0).then(|| (len - n.min(len), len - 1)),
    }
}

/// The strong entity tag of a file: its length and modification time in nanoseconds, in hex.
pub fn etag_for(len: u64, modified: SystemTime) -> String {
    let nanos = modified
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    format!("\"{len:x}-{nanos:x}\"")
}

/// `If-Range`: an entity tag must match strongly (a weak tag never matches); an HTTP-date must
/// equal the file's modification time to the second. Anything else does not match.
pub fn if_range_matches(value: &str, etag: &str, modified: SystemTime) -> bool {
    let value = value.trim();
    if value.starts_with("W/") {
        return false;
    }
    if value.starts_with('"') {
        return value == etag;
    }
    match httpdate::parse_http_date(value) {
        Ok(date) => unix_secs(date) == unix_secs(modified),
        Err(_) => false,
    }
}

/// `If-None-Match`: `*` or any listed tag equal to `etag` under weak comparison.
pub fn none_match_hits(value: &str, etag: &str) -> bool {
    let value = value.trim();
    if value == "*" {
        return true;
    }
    let bare = etag.trim_start_matches("W/");
    value
        .split(',')
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == bare)
}

/// `If-Modified-Since`: true when the file has not changed since `value` (to the second).
pub fn not_modified_since(value: &str, modified: SystemTime) -> bool {
    match httpdate::parse_http_date(value.trim()) {
        Ok(date) => unix_secs(modified) <= unix_secs(date),
        Err(_) => false,
    }
}

pub(crate) fn unix_secs(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn parses_the_three_forms() {
        assert_eq!(parse_range("bytes=0-9"), Some(ByteRangeSpec::FromTo(0, 9)));
        assert_eq!(parse_range("bytes=5-"), Some(ByteRangeSpec::From(5)));
        assert_eq!(parse_range("bytes=-3"), Some(ByteRangeSpec::Suffix(3)));
        assert_eq!(
            parse_range("Bytes = 1-2 "),
            Some(ByteRangeSpec::FromTo(1, 2))
        );
        assert_eq!(
            parse_range("bytes=0-99999999999999999999999"),
            Some(ByteRangeSpec::FromTo(0, u64::MAX))
        );
    }

    #[test]
    fn ignores_invalid_and_multiple() {
        for bad in [
            "bytes=9-0",
            "bytes=-",
            "bytes=a-b",
            "items=0-1",
            "bytes 0-1",
            "bytes=",
            "bytes=+1-2",
            "bytes=0-1,2-3",
            "bytes=0-1,x",
        ] {
            assert_eq!(parse_range(bad), None, "{bad}");
        }
    }

    #[test]
    fn resolves_against_length() {
        use ByteRangeSpec::*;
        assert_eq!(resolve(FromTo(0, 9), 100), Some((0, 9)));
        assert_eq!(resolve(FromTo(90, 200), 100), Some((90, 99)));
        assert_eq!(resolve(FromTo(100, 200), 100), None);
        assert_eq!(resolve(From(99), 100), Some((99, 99)));
        assert_eq!(resolve(From(100), 100), None);
        assert_eq!(resolve(Suffix(10), 100), Some((90, 99)));
        assert_eq!(resolve(Suffix(1000), 100), Some((0, 99)));
        assert_eq!(resolve(Suffix(0), 100), None);
        assert_eq!(resolve(Suffix(5), 0), None);
        assert_eq!(resolve(From(0), 0), None);
    }

    #[test]
    fn validators() {
        let t = UNIX_EPOCH + Duration::new(1_700_000_000, 123);
        let tag = etag_for(42, t);
        assert!(if_range_matches(&tag, &tag, t));
        assert!(!if_range_matches("\"other\"", &tag, t));
        assert!(!if_range_matches(&format!("W/{tag}"), &tag, t));
        let date = httpdate::fmt_http_date(t);
        assert!(if_range_matches(&date, &tag, t));
        assert!(!if_range_matches(&date, &tag, t + Duration::from_secs(1)));
        assert!(!if_range_matches("garbage", &tag, t));
        assert!(none_match_hits(&format!("\"x\", W/{tag}"), &tag));
        assert!(none_match_hits("*", &tag));
        assert!(!none_match_hits("\"x\"", &tag));
        assert!(not_modified_since(&date, t));
        assert!(!not_modified_since(&date, t + Duration::from_secs(1)));
    }
}
