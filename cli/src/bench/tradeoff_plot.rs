//! Scatter plots for `msth bench tradeoff`: labelled points with the Pareto front marked, drawn
//! with `plotters` into an in-memory RGB buffer (no system font or image libraries). Text needs a
//! TrueType font, found at run time ([`ensure_font`]): none is bundled.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{anyhow, Result};
use plotters::prelude::*;
use plotters::style::FontStyle;

use msth_dataset::Image8;

/// One point of a plot.
#[derive(Clone, Debug)]
pub struct PlotPoint {
    pub x: f64,
    pub y: f64,
    pub label: String,
    /// On the Pareto front (drawn filled, joined by the front line).
    pub front: bool,
}

/// Plot size in pixels.
pub const WIDTH: u32 = 960;
pub const HEIGHT: u32 = 640;

/// Font files tried first, then any `.ttf` under the usual font folders.
const CANDIDATES: [&str; 6] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation/LiberationSans-Regular.ttf",
    "/Library/Fonts/Arial.ttf",
];

/// Finds a TrueType font: `$MSTH_FONT`, a few well-known files, else the first regular-looking
/// `.ttf` under `/usr/share/fonts`, `/usr/local/share/fonts` or `~/.fonts` (4 levels deep).
pub fn find_font() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("MSTH_FONT") {
        let p = PathBuf::from(p);
        return p.is_file().then_some(p);
    }
    for c in CANDIDATES {
        if Path::new(c).is_file() {
            return Some(c.into());
        }
    }
    let mut roots = vec![
        PathBuf::from("/usr/share/fonts"),
        PathBuf::from("/usr/local/share/fonts"),
    ];
    if let Some(h) = std::env::var_os("HOME") {
        roots.push(Path::new(&h).join(".fonts"));
    }
    let mut found = Vec::new();
    for r in roots {
        walk(&r, 4, &mut found);
    }
    found.sort();
    let plain = |p: &PathBuf| {
        let n = p
            .file_name()
            .map(|n| n.to_string_lossy().to_lowercase())
            .unwrap_or_default();
        !["bold", "italic", "oblique", "mono"]
            .iter()
            .any(|w| n.contains(w))
    };
    found.iter().find(|p| plain(p)).or(found.first()).cloned()
}

fn walk(dir: &Path, depth: usize, out: &mut Vec<PathBuf>) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    for e in rd.flatten() {
        let p = e.path();
        if p.is_dir() && depth > 0 {
            walk(&p, depth - 1, out);
        } else if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("ttf")) {
            out.push(p);
        }
    }
}

/// Registers a font as plotters' `sans-serif` once per process; returns its file, or `None`
/// when no usable font was found (then no text can be drawn and the plots are skipped).
pub fn ensure_font() -> Option<PathBuf> {
    static FONT: OnceLock<Option<PathBuf>> = OnceLock::new();
    FONT.get_or_init(|| {
        let p = find_font()?;
        let bytes = std::fs::read(&p).ok()?;
        // plotters keeps fonts for the life of the process.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
            .ok()
            .map(|_| p)
    })
    .clone()
}

/// `v` with 3 significant digits, no trailing zeros (axis ticks).
fn sig3(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let digits = (2 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// A log axis's tick label: [`sig3`] at the ticks whose leading digit is 1, 2 or 5, none at the
/// others (labels at 600, 700, 800, 900 and 1000 run into each other).
fn log_tick(v: f64) -> String {
    if !(v.is_finite() && v > 0.0) {
        return String::new();
    }
    let lead = v / 10f64.powf(v.log10().floor());
    if [1.0, 2.0, 5.0, 10.0]
        .iter()
        .any(|d| (lead - d).abs() < 1e-6 * d)
    {
        sig3(v)
    } else {
        String::new()
    }
}

fn range(vals: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = vals.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let pad = if hi > lo { 0.08 * (hi - lo) } else { 1.0 };
    (lo - pad, hi + pad)
}

/// Estimated label box (pixels) for `label` at 13 px: its width and height.
fn label_size(label: &str) -> (i32, i32) {
    (7 * label.chars().count() as i32 + 2, 15)
}

/// Overlap area of two pixel rectangles `(x, y, w, h)`.
fn overlap(a: (i32, i32, i32, i32), b: (i32, i32, i32, i32)) -> i64 {
    let w = (a.0 + a.2).min(b.0 + b.2) - a.0.max(b.0);
    let h = (a.1 + a.3).min(b.1 + b.3) - a.1.max(b.1);
    if w > 0 && h > 0 {
        w as i64 * h as i64
    } else {
        0
    }
}

/// Label offsets (from the marker's pixel) that overlap other labels and markers least, chosen
/// greedily point by point.
fn place_labels(anchors: &[(i32, i32)], labels: &[&str], area: (i32, i32)) -> Vec<(i32, i32)> {
    let markers: Vec<_> = anchors
        .iter()
        .map(|&(x, y)| (x - 6, y - 6, 12, 12))
        .collect();
    let mut placed: Vec<(i32, i32, i32, i32)> = Vec::new();
    let mut out = Vec::new();
    for (i, &(x, y)) in anchors.iter().enumerate() {
        let (w, h) = label_size(labels[i]);
        let candidates = [
            (8, -16),
            (8, 2),
            (-w - 8, -16),
            (-w - 8, 2),
            (-w / 2, -24),
            (-w / 2, 9),
            (8, -30),
            (8, 16),
            (-w - 8, -30),
            (-w - 8, 16),
        ];
        let best = candidates
            .iter()
            .map(|&(dx, dy)| {
                let r = (x + dx, y + dy, w, h);
                let mut cost: i64 = placed.iter().map(|&p| overlap(r, p)).sum::<i64>() * 4;
                cost += markers.iter().map(|&m| overlap(r, m)).sum::<i64>();
                // Leaving the drawing area is worst.
                if r.0 < 0 || r.1 < 0 || r.0 + r.2 > area.0 || r.1 + r.3 > area.1 {
                    cost += 1_000_000;
                }
                (cost, (dx, dy))
            })
            .min_by_key(|c| c.0)
            .map(|c| c.1)
            .unwrap_or((8, -16));
        placed.push((x + best.0, y + best.1, w, h));
        out.push(best);
    }
    out
}

/// The corner of the plot with the fewest points near it (for the legend).
fn legend_corner(anchors: &[(i32, i32)], area: (i32, i32)) -> SeriesLabelPosition {
    let (w, h) = (area.0 / 3, area.1 / 4);
    let corners = [
        (
            SeriesLabelPosition::LowerRight,
            (area.0 - w, area.1 - h - 60),
        ),
        (SeriesLabelPosition::UpperRight, (area.0 - w, 40)),
        (SeriesLabelPosition::LowerLeft, (60, area.1 - h - 60)),
        (SeriesLabelPosition::UpperLeft, (60, 40)),
    ];
    corners
        .into_iter()
        .min_by_key(|(_, (x, y))| {
            anchors
                .iter()
                .filter(|a| a.0 >= *x && a.0 <= x + w && a.1 >= *y && a.1 <= y + h)
                .count()
        })
        .map(|c| c.0)
        .unwrap_or(SeriesLabelPosition::LowerRight)
}

/// Writes an RGB buffer of `w x h` pixels (a plot drawn with plotters' bitmap backend) as a PNG,
/// atomically, and says so.
pub fn save_rgb(path: &Path, w: u32, h: u32, buf: Vec<u8>) -> Result<()> {
    let img = Image8 {
        width: w,
        height: h,
        data: buf.into(),
    };
    msth_dataset::imageio::save_png_atomic(path, &img)
        .map_err(|e| anyhow!("writing {}: {e}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

/// Draws a labelled scatter plot (x on a log axis when `log_x`), the front points filled red
/// and joined in x order, the others hollow blue, labels placed to avoid each other. Points
/// with a non-finite coordinate (or x <= 0 on a log axis) are left out. Needs
/// [`ensure_font`] to have found a font.
pub fn scatter(
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    points: &[PlotPoint],
) -> Result<Image8> {
    if ensure_font().is_none() {
        return Err(anyhow!(
            "no TrueType font found for the plot labels (set MSTH_FONT=FILE.ttf)"
        ));
    }
    let pts: Vec<&PlotPoint> = points
        .iter()
        .filter(|p| p.x.is_finite() && p.y.is_finite() && (!log_x || p.x > 0.0))
        .collect();
    let (y0, y1) = range(pts.iter().map(|p| p.y));
    let (w, h) = (WIDTH as usize, HEIGHT as usize);
    let mut buf = vec![255u8; w * h * 3];
    let e = |e: &dyn std::fmt::Debug| anyhow!("drawing the plot `{title}`: {e:?}");
    let red = RGBColor(200, 30, 30);
    let blue = RGBColor(40, 90, 180);
    let mut front: Vec<(f64, f64)> = pts.iter().filter(|p| p.front).map(|p| (p.x, p.y)).collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        // The same drawing for a linear and a log x axis (different coordinate types).
        macro_rules! draw {
            ($xspec:expr, $xfmt:expr) => {{
                let mut chart = ChartBuilder::on(&root)
                    .caption(title, ("sans-serif", 22))
                    .margin(18)
                    .x_label_area_size(48)
                    .y_label_area_size(64)
                    .build_cartesian_2d($xspec, y0..y1)
                    .map_err(|x| e(&x))?;
                chart
                    .configure_mesh()
                    .x_desc(x_label)
                    .y_desc(y_label)
                    .x_label_formatter(&|v| $xfmt(*v))
                    .y_label_formatter(&|v| sig3(*v))
                    .label_style(("sans-serif", 14))
                    .axis_desc_style(("sans-serif", 16))
                    .light_line_style(RGBColor(235, 235, 235))
                    .draw()
                    .map_err(|x| e(&x))?;
                chart
                    .draw_series(LineSeries::new(front.clone(), red.stroke_width(2)))
                    .map_err(|x| e(&x))?
                    .label("Pareto front")
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], red.stroke_width(2))
                    });
                chart
                    .draw_series(
                        pts.iter()
                            .filter(|p| !p.front)
                            .map(|p| Circle::new((p.x, p.y), 5, blue.stroke_width(2))),
                    )
                    .map_err(|x| e(&x))?
                    .label("dominated")
                    .legend(move |(x, y)| Circle::new((x + 10, y), 5, blue.stroke_width(2)));
                chart
                    .draw_series(
                        pts.iter()
                            .filter(|p| p.front)
                            .map(|p| Circle::new((p.x, p.y), 6, red.filled())),
                    )
                    .map_err(|x| e(&x))?;
                let anchors: Vec<(i32, i32)> = pts
                    .iter()
                    .map(|p| chart.backend_coord(&(p.x, p.y)))
                    .collect();
                let labels: Vec<&str> = pts.iter().map(|p| p.label.as_str()).collect();
                let offsets = place_labels(&anchors, &labels, (WIDTH as i32, HEIGHT as i32));
                chart
                    .draw_series(pts.iter().zip(&offsets).map(|(p, &off)| {
                        EmptyElement::at((p.x, p.y))
                            + Text::new(
                                p.label.clone(),
                                off,
                                ("sans-serif", 13).into_font().color(&BLACK),
                            )
                    }))
                    .map_err(|x| e(&x))?;
                chart
                    .configure_series_labels()
                    .position(legend_corner(&anchors, (WIDTH as i32, HEIGHT as i32)))
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK)
                    .label_font(("sans-serif", 14))
                    .draw()
                    .map_err(|x| e(&x))?;
            }};
        }
        if log_x {
            let (lo, hi) = pts
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
                    (a.min(p.x), b.max(p.x))
                });
            let (lo, hi) = if lo.is_finite() {
                (lo / 1.25, hi * 1.25)
            } else {
                (1.0, 10.0)
            };
            draw!((lo..hi).log_scale(), log_tick);
        } else {
            let (x0, x1) = range(pts.iter().map(|p| p.x));
            draw!(x0..x1, sig3);
        }
        root.present().map_err(|x| e(&x))?;
    }
    Ok(Image8 {
        width: WIDTH,
        height: HEIGHT,
        data: buf.into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sig3_formats_ticks() {
        assert_eq!(sig3(123.456), "123");
        assert_eq!(sig3(1.23456), "1.23");
        assert_eq!(sig3(0.012345), "0.0123");
        assert_eq!(sig3(20.0), "20");
        assert_eq!(sig3(0.0), "0");
    }

    #[test]
    fn log_ticks_are_labelled_at_1_2_and_5_only() {
        let labels: Vec<String> = [
            100.0, 200.0, 300.0, 500.0, 800.0, 900.0, 1000.0, 2000.0, 0.05,
        ]
        .into_iter()
        .map(log_tick)
        .collect();
        assert_eq!(
            labels,
            ["100", "200", "", "500", "", "", "1000", "2000", "0.05"]
        );
        assert_eq!(log_tick(0.0), "");
    }
}
