//! RFC 9110 byte ranges, validators and preconditions, as pure functions over header strings:
//! parsing `Range` (section 14.2) and planning the answer to it against a length (14.1.2, 14.6),
//! entity-tag lists and their strong and weak comparison (8.8.3.2), `If-Match` (13.1.1),
//! `If-None-Match` (13.1.2), `If-Modified-Since` (13.1.3), `If-Unmodified-Since` (13.1.4),
//! `If-Range` (13.1.5), the order in which they are evaluated (13.2.2, [`evaluate_preconditions`])
//! and the strong entity tag this server gives a file. No I/O lives here.
//!
//! Range policy ([`plan_ranges`]):
//! - a `Range` that is syntactically invalid, names another unit, or lists more than
//!   [`MAX_RANGE_SPECS`] ranges is ignored and the whole file is sent with 200 (RFC 9110 §14.2
//!   lets a server ignore `Range`);
//! - the satisfiable ranges are sorted, and overlapping or adjacent ones merged (§14.6 lets a
//!   server coalesce regardless of the order asked); one range left: a plain 206, several: a
//!   `multipart/byteranges` 206 whose parts are in ascending order; none: 416.
//!
//! So a response never carries a byte of the file twice; and when a multipart body (parts plus
//! their headers) would be longer than the whole file, the server sends the whole file with 200
//! instead: many, small or overlapping ranges cannot make a response larger than the file.

use std::time::{SystemTime, UNIX_EPOCH};

/// Most range specs one `Range` header may list; with more it is ignored (200, whole file).
pub const MAX_RANGE_SPECS: usize = 16;

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

/// Parses a `Range` header value into its 1 to [`MAX_RANGE_SPECS`] specs, in the order given.
/// `None` means "ignore it and send the full body": invalid syntax (in any spec), a unit other
/// than `bytes`, no spec, or more than [`MAX_RANGE_SPECS`] specs.
pub fn parse_range(value: &str) -> Option<Vec<ByteRangeSpec>> {
    let value = value.trim();
    let (unit, set) = value.split_once('=')?;
    if !unit.trim().eq_ignore_ascii_case("bytes") {
        return None;
    }
    let mut parsed = Vec::new();
    // RFC 9110 §5.6.1: empty list elements are allowed and ignored.
    for spec in set.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        if parsed.len() == MAX_RANGE_SPECS {
            return None;
        }
        parsed.push(parse_spec(spec)?);
    }
    (!parsed.is_empty()).then_some(parsed)
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

/// How to answer a `Range` against a representation of some length (see the module policy).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RangePlan {
    /// 206 with one `Content-Range: bytes first-last/len`; inclusive.
    Single(u64, u64),
    /// 206 `multipart/byteranges`: 2 to [`MAX_RANGE_SPECS`] inclusive ranges, ascending,
    /// disjoint and not adjacent.
    Multi(Vec<(u64, u64)>),
    /// 416 with `Content-Range: bytes */len`: no spec overlaps the representation.
    Unsatisfiable,
}

/// Resolves every spec against `len`, drops the unsatisfiable ones (RFC 9110 §14.1.2: the set is
/// satisfiable when any one is), sorts them and merges those that overlap or touch.
pub fn plan_ranges(specs: &[ByteRangeSpec], len: u64) -> RangePlan {
    let mut ranges: Vec<(u64, u64)> = specs.iter().filter_map(|&s| resolve(s, len)).collect();
    ranges.sort_unstable();
    let mut merged: Vec<(u64, u64)> = Vec::with_capacity(ranges.len());
    for (first, last) in ranges {
        match merged.last_mut() {
            Some(prev) if first <= prev.1.saturating_add(1) => prev.1 = prev.1.max(last),
            _ => merged.push((first, last)),
        }
    }
    match merged.as_slice() {
        [] => RangePlan::Unsatisfiable,
        [(first, last)] => RangePlan::Single(*first, *last),
        _ => RangePlan::Multi(merged),
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

/// One entity tag (RFC 9110 §8.8.3): `opaque` keeps its double quotes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EntityTag<'a> {
    pub weak: bool,
    pub opaque: &'a str,
}

impl EntityTag<'_> {
    /// §8.8.3.2: both strong and the opaque tags equal octet for octet.
    pub fn strong_eq(&self, other: &EntityTag<'_>) -> bool {
        !self.weak && !other.weak && self.opaque == other.opaque
    }

    /// §8.8.3.2: the opaque tags equal, either or both may be weak.
    pub fn weak_eq(&self, other: &EntityTag<'_>) -> bool {
        self.opaque == other.opaque
    }
}

/// Parses one entity tag at the start of `s` (`W/"..."` or `"..."`); returns it and the rest.
fn take_entity_tag(s: &str) -> Option<(EntityTag<'_>, &str)> {
    let (weak, body) = match s.strip_prefix("W/") {
        Some(rest) => (true, rest),
        None => (false, s),
    };
    let inner = body.strip_prefix('"')?;
    let close = inner.find('"')?;
    // etagc = %x21 / %x23-7E / obs-text: no spaces, controls or quotes inside.
    if !inner[..close]
        .bytes()
        .all(|b| b == 0x21 || (0x23..=0x7e).contains(&b) || b >= 0x80)
    {
        return None;
    }
    Some((
        EntityTag {
            weak,
            opaque: &body[..close + 2],
        },
        &inner[close + 1..],
    ))
}

/// Exactly one entity tag (surrounding whitespace allowed), else `None`.
pub fn parse_entity_tag(value: &str) -> Option<EntityTag<'_>> {
    match take_entity_tag(value.trim())? {
        (tag, "") => Some(tag),
        _ => None,
    }
}

/// What an `If-Match` / `If-None-Match` value names: `*` (any current representation) or a list
/// of entity tags.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TagCondition<'a> {
    Any,
    Tags(Vec<EntityTag<'a>>),
}

/// Parses `"*" / #entity-tag` (RFC 9110 §13.1.1); `None` when malformed. Empty list elements
/// are skipped (§5.6.1); an empty list is malformed.
pub fn parse_tag_condition(value: &str) -> Option<TagCondition<'_>> {
    let value = value.trim();
    if value == "*" {
        return Some(TagCondition::Any);
    }
    let mut tags = Vec::new();
    let mut rest = value;
    loop {
        rest = rest.trim_start_matches([' ', '\t', ',']);
        if rest.is_empty() {
            break;
        }
        let (tag, after) = take_entity_tag(rest)?;
        tags.push(tag);
        rest = after.trim_start_matches([' ', '\t']);
        if !(rest.is_empty() || rest.starts_with(',')) {
            return None;
        }
    }
    (!tags.is_empty()).then_some(TagCondition::Tags(tags))
}

/// `If-Match` (§13.1.1): true for `*` (the file exists), or when any listed tag matches `etag`
/// under **strong** comparison. A malformed value is false: the client asked for a condition
/// that cannot be shown to hold.
pub fn if_match_holds(value: &str, etag: &str) -> bool {
    let Some(current) = parse_entity_tag(etag) else {
        return false;
    };
    match parse_tag_condition(value) {
        Some(TagCondition::Any) => true,
        Some(TagCondition::Tags(tags)) => tags.iter().any(|t| t.strong_eq(&current)),
        None => false,
    }
}

/// `If-None-Match` (§13.1.2) "hits" (the condition is false): `*`, or any listed tag equal to
/// `etag` under **weak** comparison. A malformed value never hits.
pub fn none_match_hits(value: &str, etag: &str) -> bool {
    let Some(current) = parse_entity_tag(etag) else {
        return false;
    };
    match parse_tag_condition(value) {
        Some(TagCondition::Any) => true,
        Some(TagCondition::Tags(tags)) => tags.iter().any(|t| t.weak_eq(&current)),
        None => false,
    }
}

/// `If-Range` (§13.1.5): an entity tag must match strongly (a weak tag never matches); an
/// HTTP-date must equal the file's modification time to the second. Anything else does not
/// match.
pub fn if_range_matches(value: &str, etag: &str, modified: SystemTime) -> bool {
    let value = value.trim();
    if value.starts_with("W/") || value.starts_with('"') {
        return match (parse_entity_tag(value), parse_entity_tag(etag)) {
            (Some(asked), Some(current)) => asked.strong_eq(&current),
            _ => false,
        };
    }
    match httpdate::parse_http_date(value) {
        Ok(date) => unix_secs(date) == unix_secs(modified),
        Err(_) => false,
    }
}

/// `If-Modified-Since` (§13.1.3): true when the file has not changed since `value` (to the
/// second), i.e. the condition is false and a GET gets 304. An invalid date: false.
pub fn not_modified_since(value: &str, modified: SystemTime) -> bool {
    match httpdate::parse_http_date(value.trim()) {
        Ok(date) => unix_secs(modified) <= unix_secs(date),
        Err(_) => false,
    }
}

/// `If-Unmodified-Since` (§13.1.4): `Some(true)` when the file was last modified at or before
/// `value` (to the second), `Some(false)` when after; `None` when the value is not a valid
/// HTTP-date (the field is then ignored, as the RFC requires).
pub fn unmodified_since(value: &str, modified: SystemTime) -> Option<bool> {
    let date = httpdate::parse_http_date(value.trim()).ok()?;
    Some(unix_secs(modified) <= unix_secs(date))
}

/// The conditional header fields of a `GET`/`HEAD` request, as received. A list field sent in
/// several lines is given joined with `", "`; a date field sent more than once is given as `None`
/// (§13.1.3 and §13.1.4: ignore a value that is not one valid date).
#[derive(Debug, Clone, Copy, Default)]
pub struct Conditions<'a> {
    pub if_match: Option<&'a str>,
    pub if_unmodified_since: Option<&'a str>,
    pub if_none_match: Option<&'a str>,
    pub if_modified_since: Option<&'a str>,
}

/// The outcome of the preconditions of a `GET`/`HEAD` (`If-Range` is judged afterwards, with
/// the `Range` it guards).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precondition {
    /// Go on: `If-Range`/`Range`, then 200 or 206.
    Proceed,
    /// 304 Not Modified.
    NotModified,
    /// 412 Precondition Failed.
    Failed,
}

/// RFC 9110 §13.2.2, steps 1 to 4, for a `GET`/`HEAD` of an existing file with strong entity tag
/// `etag` and modification time `modified`:
/// 1. `If-Match` present: false -> 412; true -> step 3.
/// 2. else `If-Unmodified-Since` present (and a valid date): false -> 412.
/// 3. `If-None-Match` present: false -> 304; true -> step 5 (proceed).
/// 4. else `If-Modified-Since` present (and a valid date): false -> 304.
pub fn evaluate_preconditions(
    c: &Conditions<'_>,
    etag: &str,
    modified: SystemTime,
) -> Precondition {
    match c.if_match {
        Some(v) => {
            if !if_match_holds(v, etag) {
                return Precondition::Failed;
            }
        }
        None => {
            if c.if_unmodified_since
                .and_then(|v| unmodified_since(v, modified))
                == Some(false)
            {
                return Precondition::Failed;
            }
        }
    }
    let not_modified = match c.if_none_match {
        Some(v) => none_match_hits(v, etag),
        None => c
            .if_modified_since
            .is_some_and(|v| not_modified_since(v, modified)),
    };
    if not_modified {
        Precondition::NotModified
    } else {
        Precondition::Proceed
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
        use ByteRangeSpec::*;
        assert_eq!(parse_range("bytes=0-9"), Some(vec![FromTo(0, 9)]));
        assert_eq!(parse_range("bytes=5-"), Some(vec![From(5)]));
        assert_eq!(parse_range("bytes=-3"), Some(vec![Suffix(3)]));
        assert_eq!(parse_range("Bytes = 1-2 "), Some(vec![FromTo(1, 2)]));
        assert_eq!(
            parse_range("bytes=0-99999999999999999999999"),
            Some(vec![FromTo(0, u64::MAX)])
        );
        assert_eq!(
            parse_range("bytes=0-1, 5-6,,-2"),
            Some(vec![FromTo(0, 1), FromTo(5, 6), Suffix(2)])
        );
    }

    #[test]
    fn ignores_invalid_and_too_many() {
        for bad in [
            "bytes=9-0",
            "bytes=-",
            "bytes=a-b",
            "items=0-1",
            "bytes 0-1",
            "bytes=",
            "bytes=,",
            "bytes=+1-2",
            "bytes=0-1,x",
            "bytes=0-1,3-2",
        ] {
            assert_eq!(parse_range(bad), None, "{bad}");
        }
        let at_limit = vec!["0-0"; MAX_RANGE_SPECS].join(",");
        assert_eq!(
            parse_range(&format!("bytes={at_limit}")).map(|v| v.len()),
            Some(MAX_RANGE_SPECS)
        );
        let over = vec!["0-0"; MAX_RANGE_SPECS + 1].join(",");
        assert_eq!(parse_range(&format!("bytes={over}")), None);
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
    fn plans_single_multi_and_coalesced_ranges() {
        let plan = |v: &str, len| plan_ranges(&parse_range(v).unwrap(), len);
        assert_eq!(
            plan("bytes=0-1,5-6", 100),
            RangePlan::Multi(vec![(0, 1), (5, 6)])
        );
        // Ascending order, whatever the order asked.
        assert_eq!(
            plan("bytes=5-6,0-1", 100),
            RangePlan::Multi(vec![(0, 1), (5, 6)])
        );
        // Overlapping and adjacent ranges are merged; a repeated range is sent once.
        assert_eq!(plan("bytes=0-4,3-9,10-12", 100), RangePlan::Single(0, 12));
        assert_eq!(plan("bytes=0-9,0-9,0-9,0-9", 100), RangePlan::Single(0, 9));
        assert_eq!(plan("bytes=0-,-10", 100), RangePlan::Single(0, 99));
        // Unsatisfiable specs are dropped; 416 only when none is left.
        assert_eq!(plan("bytes=200-300,5-6", 100), RangePlan::Single(5, 6));
        assert_eq!(plan("bytes=200-300,100-", 100), RangePlan::Unsatisfiable);
        assert_eq!(plan("bytes=0-1", 0), RangePlan::Unsatisfiable);
        // Whatever is asked, the parts are disjoint: no byte of the file is sent twice.
        let many = (0..MAX_RANGE_SPECS)
            .map(|i| format!("{}-{}", i * 3, i * 3 + 50))
            .collect::<Vec<_>>()
            .join(",");
        assert_eq!(
            plan(&format!("bytes={many}"), 1000),
            RangePlan::Single(0, (MAX_RANGE_SPECS as u64 - 1) * 3 + 50)
        );
    }

    #[test]
    fn entity_tags_and_comparison() {
        let strong = parse_entity_tag("\"a\"").unwrap();
        let weak = parse_entity_tag(" W/\"a\" ").unwrap();
        assert_eq!(
            strong,
            EntityTag {
                weak: false,
                opaque: "\"a\""
            }
        );
        assert!(weak.weak);
        // RFC 9110 §8.8.3.2's table.
        assert!(strong.strong_eq(&strong) && strong.weak_eq(&strong));
        assert!(!weak.strong_eq(&weak) && weak.weak_eq(&weak));
        assert!(!weak.strong_eq(&strong) && weak.weak_eq(&strong));
        let b = parse_entity_tag("\"b\"").unwrap();
        assert!(!strong.strong_eq(&b) && !strong.weak_eq(&b));
        for bad in ["a", "\"a", "\"a\" \"b\"", "w/\"a\"", "\"a b\"", ""] {
            assert_eq!(parse_entity_tag(bad), None, "{bad}");
        }
        assert_eq!(parse_tag_condition(" * "), Some(TagCondition::Any));
        assert_eq!(
            parse_tag_condition("\"x\", W/\"y\" ,").map(|c| match c {
                TagCondition::Tags(t) => t.len(),
                TagCondition::Any => 0,
            }),
            Some(2)
        );
        // A comma inside a tag is part of it, not a separator.
        assert_eq!(
            parse_tag_condition("\"a,b\""),
            Some(TagCondition::Tags(vec![EntityTag {
                weak: false,
                opaque: "\"a,b\""
            }]))
        );
        for bad in ["", ",", "\"x\" junk", "x", "*, \"x\""] {
            assert_eq!(parse_tag_condition(bad), None, "{bad}");
        }
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
        // If-Match compares strongly: the weak form of the current tag does not match.
        assert!(if_match_holds(&tag, &tag));
        assert!(if_match_holds(&format!("\"x\", {tag}"), &tag));
        assert!(if_match_holds("*", &tag));
        assert!(!if_match_holds(&format!("W/{tag}"), &tag));
        assert!(!if_match_holds("\"other\"", &tag));
        assert!(!if_match_holds("garbage", &tag));
        assert_eq!(unmodified_since(&date, t), Some(true));
        assert_eq!(
            unmodified_since(&date, t + Duration::from_secs(1)),
            Some(false)
        );
        assert_eq!(unmodified_since("yesterday", t), None);
    }

    /// One case per rule of RFC 9110 §13.2.2 steps 1-4.
    #[test]
    fn precondition_order() {
        use Precondition::*;
        let t = UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let tag = etag_for(42, t);
        let before = httpdate::fmt_http_date(t - Duration::from_secs(60));
        let at = httpdate::fmt_http_date(t);
        let eval = |c: Conditions<'_>| evaluate_preconditions(&c, &tag, t);
        let none = Conditions::default();
        assert_eq!(eval(none), Proceed);
        // Step 1: If-Match false -> 412, true -> on to step 3.
        assert_eq!(
            eval(Conditions {
                if_match: Some("\"other\""),
                ..none
            }),
            Failed
        );
        assert_eq!(
            eval(Conditions {
                if_match: Some(&tag),
                ..none
            }),
            Proceed
        );
        // Step 1 wins over If-Unmodified-Since, which is then ignored (true or false).
        assert_eq!(
            eval(Conditions {
                if_match: Some(&tag),
                if_unmodified_since: Some(&before),
                ..none
            }),
            Proceed
        );
        assert_eq!(
            eval(Conditions {
                if_match: Some("\"x\""),
                if_unmodified_since: Some(&at),
                ..none
            }),
            Failed
        );
        // Step 2: If-Unmodified-Since before the modification -> 412; at it -> proceed;
        // not a date -> ignored.
        assert_eq!(
            eval(Conditions {
                if_unmodified_since: Some(&before),
                ..none
            }),
            Failed
        );
        assert_eq!(
            eval(Conditions {
                if_unmodified_since: Some(&at),
                ..none
            }),
            Proceed
        );
        assert_eq!(
            eval(Conditions {
                if_unmodified_since: Some("soon"),
                ..none
            }),
            Proceed
        );
        // Step 3: If-None-Match matching (weakly) -> 304, after a true If-Match.
        let weak = format!("W/{tag}");
        assert_eq!(
            eval(Conditions {
                if_none_match: Some(&weak),
                ..none
            }),
            NotModified
        );
        assert_eq!(
            eval(Conditions {
                if_match: Some(&tag),
                if_none_match: Some(&tag),
                ..none
            }),
            NotModified
        );
        // A failed If-Match is 412 even when If-None-Match would give 304 (step 1 comes first).
        assert_eq!(
            eval(Conditions {
                if_match: Some("\"x\""),
                if_none_match: Some(&tag),
                ..none
            }),
            Failed
        );
        // Step 3 wins over If-Modified-Since, which is then ignored.
        assert_eq!(
            eval(Conditions {
                if_none_match: Some("\"x\""),
                if_modified_since: Some(&at),
                ..none
            }),
            Proceed
        );
        // Step 4: If-Modified-Since at or after the modification -> 304, before -> proceed.
        assert_eq!(
            eval(Conditions {
                if_modified_since: Some(&at),
                ..none
            }),
            NotModified
        );
        assert_eq!(
            eval(Conditions {
                if_modified_since: Some(&before),
                ..none
            }),
            Proceed
        );
    }
}
