//! `tacos-ground plot`: a mission's trajectories over the map, coloured by speed (blue slow, red
//! fast), as the paper's figures show them. Written as SVG by hand: no drawing library needed.

use crate::mission::log::{Line, Record};
use std::collections::BTreeMap;
use std::fmt::Write;
use tacos_shared::scenario::Scenario;
use tacos_shared::world::LandmarkKind;

const WIDTH: f64 = 1000.0;
const MARGIN: f64 = 40.0;

struct Frame {
    min_x: f64,
    max_y: f64,
    scale: f64,
}

impl Frame {
    fn px(&self, x: f64, y: f64) -> (f64, f64) {
        (
            MARGIN + (x - self.min_x) * self.scale,
            MARGIN + (self.max_y - y) * self.scale,
        )
    }
}

fn kind_colour(kind: LandmarkKind) -> &'static str {
    match kind {
        LandmarkKind::Car => "#7f7f7f",
        LandmarkKind::Villa => "#c49c6b",
        LandmarkKind::Tree => "#2e8b3a",
        LandmarkKind::Skyscraper => "#404a5a",
        LandmarkKind::Pad => "#e0a000",
        LandmarkKind::Park => "#5fbf5f",
        LandmarkKind::District => "#6a6aa0",
        LandmarkKind::Building => "#8a6a50",
    }
}

/// Blue → cyan → yellow → red as `t` goes 0 → 1.
pub fn speed_colour(t: f64) -> String {
    let t = t.clamp(0.0, 1.0);
    let stops = [
        (0.0, (40.0, 60.0, 220.0)),
        (0.35, (40.0, 200.0, 220.0)),
        (0.7, (240.0, 210.0, 40.0)),
        (1.0, (220.0, 40.0, 30.0)),
    ];
    let mut out = stops[0].1;
    for w in stops.windows(2) {
        let ((t0, c0), (t1, c1)) = (w[0], w[1]);
        if t >= t0 && t <= t1 {
            let f = (t - t0) / (t1 - t0);
            out = (
                c0.0 + f * (c1.0 - c0.0),
                c0.1 + f * (c1.1 - c0.1),
                c0.2 + f * (c1.2 - c0.2),
            );
        }
    }
    format!("#{:02x}{:02x}{:02x}", out.0 as u8, out.1 as u8, out.2 as u8)
}

impl Frame {
    /// The map's frame in the picture, and the picture's height.
    fn of(scenario: &Scenario) -> (Frame, f64) {
        let b = &scenario.world.bounds;
        let span_x = (b.max.x - b.min.x).max(1e-6);
        let span_y = (b.max.y - b.min.y).max(1e-6);
        let scale = (WIDTH - 2.0 * MARGIN) / span_x;
        let height = span_y * scale + 2.0 * MARGIN + 40.0;
        let frame = Frame {
            min_x: b.min.x,
            max_y: b.max.y,
            scale,
        };
        (frame, height)
    }
}

/// The SVG picture of a mission log over its scenario's map.
pub fn svg(lines: &[Line], scenario: &Scenario) -> String {
    let b = &scenario.world.bounds;
    let span_x = (b.max.x - b.min.x).max(1e-6);
    let span_y = (b.max.y - b.min.y).max(1e-6);
    let (f, height) = Frame::of(scenario);
    let scale = f.scale;
    let mut out = String::new();
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH:.0}" height="{height:.0}" viewBox="0 0 {WIDTH:.0} {height:.0}" font-family="sans-serif" font-size="10">"#
    );
    let _ = writeln!(
        out,
        r##"<rect x="0" y="0" width="{WIDTH:.0}" height="{height:.0}" fill="#ffffff"/>"##
    );
    let (x0, y0) = f.px(b.min.x, b.max.y);
    let _ = writeln!(
        out,
        r##"<rect x="{x0:.1}" y="{y0:.1}" width="{:.1}" height="{:.1}" fill="#f4f6f0" stroke="#333" stroke-width="1"/>"##,
        span_x * scale,
        span_y * scale
    );

    for o in &scenario.world.obstacles {
        // The footprint: the ellipsoid projected on the ground plane (a Schur complement).
        let a = &o.shape;
        let azz = a[(2, 2)].max(1e-12);
        let m = nalgebra_2x2([
            [
                a[(0, 0)] - a[(0, 2)] * a[(2, 0)] / azz,
                a[(0, 1)] - a[(0, 2)] * a[(2, 1)] / azz,
            ],
            [
                a[(1, 0)] - a[(1, 2)] * a[(2, 0)] / azz,
                a[(1, 1)] - a[(1, 2)] * a[(2, 1)] / azz,
            ],
        ]);
        let (rx, ry, angle) = m;
        let (cx, cy) = f.px(o.center.x, o.center.y);
        let _ = writeln!(
            out,
            r##"<ellipse cx="{cx:.1}" cy="{cy:.1}" rx="{:.1}" ry="{:.1}" transform="rotate({:.1} {cx:.1} {cy:.1})" fill="#404a5a" fill-opacity="0.35" stroke="#404a5a"/>"##,
            rx * scale,
            ry * scale,
            -angle.to_degrees()
        );
    }
    for l in &scenario.world.landmarks {
        let (x, y) = f.px(l.position.x, l.position.y);
        let colour = kind_colour(l.kind);
        let _ = writeln!(
            out,
            r#"<rect x="{:.1}" y="{:.1}" width="6" height="6" fill="{colour}"><title>{} ({})</title></rect>"#,
            x - 3.0,
            y - 3.0,
            l.name,
            l.kind
        );
        let _ = writeln!(
            out,
            r##"<text x="{:.1}" y="{:.1}" fill="#555" font-size="7">{}</text>"##,
            x + 4.0,
            y - 3.0,
            l.name
        );
    }

    let mut tracks: BTreeMap<&str, Vec<(f64, f64, f64)>> = BTreeMap::new();
    for line in lines {
        if let Record::Position {
            drone, x, y, speed, ..
        } = &line.record
        {
            tracks
                .entry(drone.as_str())
                .or_default()
                .push((*x, *y, *speed));
        }
    }
    let max_speed = scenario.limits.max_speed.max(1e-6);
    for (drone, points) in &tracks {
        for w in points.windows(2) {
            let (a, b) = (w[0], w[1]);
            let (x1, y1) = f.px(a.0, a.1);
            let (x2, y2) = f.px(b.0, b.1);
            let colour = speed_colour(0.5 * (a.2 + b.2) / max_speed);
            let _ = writeln!(
                out,
                r#"<line x1="{x1:.1}" y1="{y1:.1}" x2="{x2:.1}" y2="{y2:.1}" stroke="{colour}" stroke-width="2" stroke-linecap="round"/>"#
            );
        }
        if let Some(last) = points.last() {
            let (x, y) = f.px(last.0, last.1);
            let _ = writeln!(
                out,
                r##"<circle cx="{x:.1}" cy="{y:.1}" r="3" fill="#000"/><text x="{:.1}" y="{:.1}" font-weight="bold">{drone}</text>"##,
                x + 5.0,
                y + 4.0
            );
        }
    }

    // Speed colour bar.
    let bar_y = height - 28.0;
    for i in 0..100 {
        let _ = writeln!(
            out,
            r#"<rect x="{:.1}" y="{bar_y:.1}" width="2.1" height="10" fill="{}"/>"#,
            MARGIN + 2.0 * i as f64,
            speed_colour(i as f64 / 99.0)
        );
    }
    let _ = writeln!(
        out,
        r#"<text x="{MARGIN:.0}" y="{:.1}">0 m/s</text><text x="{:.0}" y="{:.1}">{max_speed:.0} m/s</text>"#,
        bar_y + 22.0,
        MARGIN + 190.0,
        bar_y + 22.0
    );
    let _ = writeln!(
        out,
        r#"<text x="{:.0}" y="{:.1}">{} — {} trajectories, coloured by speed</text>"#,
        MARGIN + 260.0,
        bar_y + 9.0,
        scenario.name,
        tracks.len()
    );
    out.push_str("</svg>\n");
    out
}

/// Radii and angle of the ellipse `{p : pᵀ M p ≤ 1}` for a symmetric positive definite 2×2 M.
fn nalgebra_2x2(m: [[f64; 2]; 2]) -> (f64, f64, f64) {
    let (a, b, c) = (m[0][0], 0.5 * (m[0][1] + m[1][0]), m[1][1]);
    let mean = 0.5 * (a + c);
    let diff = (0.25 * (a - c).powi(2) + b * b).sqrt();
    let (l1, l2) = ((mean + diff).max(1e-12), (mean - diff).max(1e-12));
    let angle = 0.5 * (2.0 * b).atan2(a - c);
    // The eigenvector of l1 is at `angle`; its radius is 1/sqrt(l1).
    (1.0 / l1.sqrt(), 1.0 / l2.sqrt(), angle)
}

/// Why an SVG could not be made a PNG.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    #[error("the SVG does not parse: {0}")]
    Parse(String),
    #[error("the picture has no pixels ({0}×{1})")]
    Size(u32, u32),
    #[error("PNG encoding failed: {0}")]
    Encode(String),
}

/// The picture as PNG: `svg` rasterised by resvg at `scale` (1.0 = one pixel per SVG unit).
/// Text uses the system's fonts; without any, the picture is drawn without its labels.
pub fn png(svg: &str, scale: f32) -> Result<Vec<u8>, RasterError> {
    use resvg::{tiny_skia, usvg};
    let mut fonts = usvg::fontdb::Database::new();
    fonts.load_system_fonts();
    // The SVG asks for the generic "sans-serif", which fontdb maps to Arial unless told: name
    // a sans family this machine has.
    let has = |family: &str| {
        fonts
            .faces()
            .any(|f| f.families.iter().any(|(name, _)| name == family))
    };
    let sans = ["DejaVu Sans", "Liberation Sans", "Noto Sans", "Arial"]
        .into_iter()
        .find(|f| has(f))
        .map(str::to_owned)
        .or_else(|| {
            fonts
                .faces()
                .next()
                .and_then(|f| f.families.first().map(|(n, _)| n.clone()))
        });
    if let Some(sans) = sans {
        fonts.set_sans_serif_family(sans);
    }
    let options = usvg::Options {
        fontdb: std::sync::Arc::new(fonts),
        ..usvg::Options::default()
    };
    let tree =
        usvg::Tree::from_str(svg, &options).map_err(|e| RasterError::Parse(e.to_string()))?;
    let size = tree.size();
    let (w, h) = (
        (size.width() * scale).ceil() as u32,
        (size.height() * scale).ceil() as u32,
    );
    let mut pixmap = tiny_skia::Pixmap::new(w, h).ok_or(RasterError::Size(w, h))?;
    pixmap.fill(tiny_skia::Color::WHITE);
    resvg::render(
        &tree,
        tiny_skia::Transform::from_scale(scale, scale),
        &mut pixmap.as_mut(),
    );
    pixmap
        .encode_png()
        .map_err(|e| RasterError::Encode(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mission::log::Line;

    /// Ten positions of alfa at 10 m, one a second: `at(i)` gives x, y and speed.
    fn track(at: impl Fn(f64) -> (f64, f64, f64)) -> Vec<Line> {
        (0..10)
            .map(|i| {
                let (x, y, speed) = at(i as f64);
                Line {
                    t: i as f64,
                    record: Record::Position {
                        drone: "alfa".into(),
                        x,
                        y,
                        z: 10.0,
                        speed,
                    },
                }
            })
            .collect()
    }

    #[test]
    fn draws_the_map_and_speed_coloured_tracks() {
        let city = Scenario::builtin("city").expect("city");
        let lines = track(|i| (-40.0, -130.0 + 5.0 * i, i));
        let svg = svg(&lines, &city);
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<ellipse").count(), 4, "four skyscrapers");
        assert_eq!(svg.matches("<title>").count(), 51, "every landmark");
        assert_eq!(
            svg.matches(r#"stroke-width="2""#).count(),
            9,
            "nine track segments"
        );
        assert!(
            svg.contains(&speed_colour(0.5 * (8.0 + 9.0) / 8.0)),
            "the fastest segment is red"
        );
    }

    #[test]
    fn the_png_is_the_svg_rasterised() {
        let city = Scenario::builtin("city").expect("city");
        let lines = track(|i| (-40.0 + 5.0 * i, -130.0, 8.0));
        let bytes = png(&svg(&lines, &city), 1.0).expect("rasterised");
        assert!(bytes.starts_with(b"\x89PNG\r\n\x1a\n"));
        let image = resvg::tiny_skia::Pixmap::decode_png(&bytes).expect("decodes");
        assert_eq!(image.width(), WIDTH as u32);
        // The same frame as the SVG: the track's middle is red (fast), a tower's centre dark,
        // the margin white.
        let (f, _) = Frame::of(&city);
        let pixel = |x: f64, y: f64| {
            let (px, py) = f.px(x, y);
            let p = image
                .pixel(px as u32, py as u32)
                .expect("inside the picture");
            (p.red(), p.green(), p.blue())
        };
        let (r, g, bl) = pixel(-17.5, -130.0);
        assert!(
            r > 180 && g < 120 && bl < 120,
            "track pixel {:?}",
            (r, g, bl)
        );
        let (r, g, bl) = pixel(18.0, 18.0);
        assert!(
            r < 120 && g < 120 && bl < 140,
            "tower pixel {:?}",
            (r, g, bl)
        );
        assert_eq!(image.pixel(2, 2).map(|p| p.red()), Some(255));
        assert!(matches!(png("<svg", 1.0), Err(RasterError::Parse(_))));
    }

    #[test]
    fn footprint_of_a_round_tower() {
        let (rx, ry, _) = nalgebra_2x2([[1.0 / 64.0, 0.0], [0.0, 1.0 / 64.0]]);
        assert!((rx - 8.0).abs() < 1e-9 && (ry - 8.0).abs() < 1e-9);
        assert_eq!(speed_colour(0.0), "#283cdc");
        assert_eq!(speed_colour(1.0), "#dc281e");
    }
}
