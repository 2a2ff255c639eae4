//! The map pane: landmarks by kind, obstacle footprints, drones by mode with their trails, and
//! targets, drawn on a braille canvas over the scenario's bounds with labels beside the marks.

use super::panes::{pane, short_mode};
use super::state::{DroneRow, TerminalState};
use ratatui::buffer::Buffer;
use ratatui::layout::Rect;
use ratatui::style::{Color, Modifier, Style};
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::Widget;
use ratatui::widgets::canvas::{Canvas, Context, Line as CanvasLine, Points, Rectangle};
use tacos_shared::DroneMode;
use tacos_shared::world::{Ellipsoid, LandmarkKind};

pub fn mode_color(mode: DroneMode) -> Color {
    match mode {
        DroneMode::Idle => Color::LightBlue,
        DroneMode::Flying => Color::LightGreen,
        DroneMode::Tracking => Color::LightMagenta,
        DroneMode::Unavailable => Color::Red,
    }
}

/// The map's marker and colour for a kind of landmark.
pub fn landmark_symbol(kind: LandmarkKind) -> (char, Color) {
    match kind {
        LandmarkKind::Car => ('▪', Color::Yellow),
        LandmarkKind::Villa => ('⌂', Color::Magenta),
        LandmarkKind::Tree => ('♣', Color::Green),
        LandmarkKind::Skyscraper => ('▲', Color::White),
        LandmarkKind::Pad => ('H', Color::Cyan),
        LandmarkKind::Park => ('○', Color::LightGreen),
        LandmarkKind::District => ('#', Color::LightBlue),
        LandmarkKind::Building => ('■', Color::Gray),
    }
}

pub const DRONE_MARKER: char = '●';
pub const TARGET_MARKER: char = '◎';
const TARGET_COLOR: Color = Color::LightRed;

// ---- map -----------------------------------------------------------------------------------

/// The horizontal shadow of an ellipsoid as a closed polyline: the xy block of A⁻¹ is the
/// shadow's own inverse shape matrix; its Cholesky factor maps the unit circle onto it.
pub fn ellipse_footprint(e: &Ellipsoid, segments: usize) -> Vec<(f64, f64)> {
    let Some(inv) = e.shape.try_inverse() else {
        return Vec::new();
    };
    let (a, b, c) = (inv[(0, 0)], inv[(0, 1)], inv[(1, 1)]);
    if a.is_nan() || a <= 0.0 {
        return Vec::new();
    }
    let l11 = a.sqrt();
    let l21 = b / l11;
    let l22 = (c - l21 * l21).max(0.0).sqrt();
    (0..=segments)
        .map(|i| {
            let t = std::f64::consts::TAU * i as f64 / segments.max(1) as f64;
            let (s, co) = t.sin_cos();
            (e.center.x + l11 * co, e.center.y + l21 * co + l22 * s)
        })
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect()
}

/// Map bounds for an inner area of `cols`×`rows` cells showing `world` without distortion.
pub fn map_bounds(state: &TerminalState, cols: u16, rows: u16) -> ([f64; 2], [f64; 2]) {
    let b = &state.world.bounds;
    let (dx, dy) = ((b.max.x - b.min.x).max(1e-3), (b.max.y - b.min.y).max(1e-3));
    let (w, h) = (f64::from(cols.max(1)), f64::from(rows.max(1)) * 2.0);
    // A little room around the bounds so their frame and edge labels stay visible.
    let scale = (dx / w).max(dy / h) * 1.06;
    let (cx, cy) = ((b.min.x + b.max.x) / 2.0, (b.min.y + b.max.y) / 2.0);
    let (hx, hy) = (w * scale / 2.0, h * scale / 2.0);
    ([cx - hx, cx + hx], [cy - hy, cy + hy])
}

/// The map: bounds, obstacle footprints, landmarks by kind, trails, targets and the drones
/// coloured by mode. North (+y) is up.
pub fn render_map(state: &TerminalState, area: Rect, buf: &mut Buffer) {
    let block =
        pane(format!("map · {}", state.scenario_name), false).title_bottom(map_legend(state));
    let inner = block.inner(area);
    let (x_bounds, y_bounds) = map_bounds(state, inner.width, inner.height);
    let label_all = state.world.landmarks.len() <= 12;
    let canvas = Canvas::default()
        .block(block)
        .marker(Marker::Braille)
        .x_bounds(x_bounds)
        .y_bounds(y_bounds)
        .paint(|ctx: &mut Context| {
            let b = &state.world.bounds;
            ctx.draw(&Rectangle {
                x: b.min.x,
                y: b.min.y,
                width: b.max.x - b.min.x,
                height: b.max.y - b.min.y,
                color: Color::DarkGray,
            });
            for obstacle in &state.world.obstacles {
                let points = ellipse_footprint(obstacle, 48);
                for pair in points.windows(2) {
                    ctx.draw(&CanvasLine {
                        x1: pair[0].0,
                        y1: pair[0].1,
                        x2: pair[1].0,
                        y2: pair[1].1,
                        color: Color::Gray,
                    });
                }
            }
            ctx.layer();
            for drone in &state.drones {
                // The trail as a path that ends at the drone.
                let path: Vec<(f64, f64)> = state
                    .trails
                    .get(&drone.id)
                    .into_iter()
                    .flatten()
                    .map(|(_, p)| (p.x, p.y))
                    .chain(drone.position.map(|p| (p.x, p.y)))
                    .collect();
                let color = mode_color(drone.mode);
                for pair in path.windows(2) {
                    ctx.draw(&CanvasLine {
                        x1: pair[0].0,
                        y1: pair[0].1,
                        x2: pair[1].0,
                        y2: pair[1].1,
                        color,
                    });
                }
            }
            let targets: Vec<(f64, f64)> = state
                .targets
                .iter()
                .map(|t| (t.position.x, t.position.y))
                .collect();
            ctx.draw(&Points {
                coords: &targets,
                color: TARGET_COLOR,
            });
        });
    canvas.render(area, buf);

    // Labels, placed here rather than by the canvas so that they line up with its dots and do
    // not overwrite each other: drones first, then targets, then landmarks.
    let mut labels = MapLabels::new(inner, x_bounds, y_bounds);
    // Drones too close to label apart (a pad of ten, a formation) are one marker named after
    // the first, with how many more are there: "●alfa+4". A drone joins a group when its cell
    // would fall under the group's marker or label.
    let mut cells: Vec<((u16, u16), &DroneRow, usize)> = Vec::new();
    for drone in &state.drones {
        let Some((col, row)) = drone.position.and_then(|p| labels.cell(p.x, p.y)) else {
            continue;
        };
        let under = |((c, r), first, _): &&mut ((u16, u16), &DroneRow, usize)| {
            let span = first.id.chars().count() as u16 + 3;
            *r == row && col + 1 >= *c && col <= c.saturating_add(span)
        };
        match cells.iter_mut().find(under) {
            Some((_, _, more)) => *more += 1,
            None => cells.push(((col, row), drone, 0)),
        }
    }
    for (_, drone, more) in cells {
        if let Some(p) = drone.position {
            let style = Style::new()
                .fg(mode_color(drone.mode))
                .add_modifier(Modifier::BOLD);
            let name = match more {
                0 => drone.id.clone(),
                n => format!("{}+{n}", drone.id),
            };
            labels.place(buf, p.x, p.y, DRONE_MARKER, &name, style);
        }
    }
    for target in &state.targets {
        let style = Style::new().fg(TARGET_COLOR).add_modifier(Modifier::BOLD);
        labels.place(
            buf,
            target.position.x,
            target.position.y,
            TARGET_MARKER,
            &target.name,
            style,
        );
    }
    for landmark in &state.world.landmarks {
        let (symbol, color) = landmark_symbol(landmark.kind);
        let labelled = label_all
            || matches!(
                landmark.kind,
                LandmarkKind::Park | LandmarkKind::District | LandmarkKind::Pad
            );
        let name = if labelled { landmark.name.as_str() } else { "" };
        let style = Style::new().fg(color);
        labels.place(
            buf,
            landmark.position.x,
            landmark.position.y,
            symbol,
            name,
            style,
        );
    }
}

/// Map labels: a marker in the cell of its point and a name beside it (right if it fits, else
/// left, else cut), never over a cell an earlier label took.
struct MapLabels {
    inner: Rect,
    x_bounds: [f64; 2],
    y_bounds: [f64; 2],
    taken: Vec<bool>,
}

impl MapLabels {
    fn new(inner: Rect, x_bounds: [f64; 2], y_bounds: [f64; 2]) -> MapLabels {
        MapLabels {
            inner,
            x_bounds,
            y_bounds,
            taken: vec![false; usize::from(inner.width) * usize::from(inner.height)],
        }
    }

    /// The cell of a point, as the canvas's braille grid maps it (2×4 dots a cell).
    fn cell(&self, x: f64, y: f64) -> Option<(u16, u16)> {
        let [left, right] = self.x_bounds;
        let [bottom, top] = self.y_bounds;
        if !(x >= left && x <= right && y >= bottom && y <= top) {
            return None;
        }
        let dots_x = f64::from(self.inner.width) * 2.0 - 1.0;
        let dots_y = f64::from(self.inner.height) * 4.0 - 1.0;
        let col = ((x - left) * dots_x / (right - left)) as u16 / 2;
        let row = ((top - y) * dots_y / (top - bottom)) as u16 / 4;
        (col < self.inner.width && row < self.inner.height).then_some((col, row))
    }

    fn free(&self, col: u16, row: u16) -> bool {
        col < self.inner.width
            && !self.taken[usize::from(row) * usize::from(self.inner.width) + usize::from(col)]
    }

    fn put(&mut self, buf: &mut Buffer, col: u16, row: u16, c: char, style: Style) {
        self.taken[usize::from(row) * usize::from(self.inner.width) + usize::from(col)] = true;
        buf[(self.inner.x + col, self.inner.y + row)]
            .set_char(c)
            .set_style(style);
    }

    fn place(&mut self, buf: &mut Buffer, x: f64, y: f64, marker: char, name: &str, style: Style) {
        let Some((col, row)) = self.cell(x, y) else {
            return;
        };
        if !self.free(col, row) {
            return;
        }
        self.put(buf, col, row, marker, style);
        // One cell per character (names are ids and landmark names).
        let name: Vec<char> = name.chars().collect();
        let n = name.len() as u16;
        let right = (1..=n).all(|i| self.free(col.saturating_add(i), row));
        let left = col >= n && (1..=n).all(|i| self.free(col - i, row));
        let start = if right || !left { col + 1 } else { col - n };
        for (i, c) in name.into_iter().enumerate() {
            let at = start + i as u16;
            if !self.free(at, row) {
                break;
            }
            self.put(buf, at, row, c, style);
        }
    }
}

/// The kinds of landmark on this map, and the mode colours.
fn map_legend(state: &TerminalState) -> Line<'static> {
    let mut kinds: Vec<LandmarkKind> = Vec::new();
    for l in &state.world.landmarks {
        if !kinds.contains(&l.kind) {
            kinds.push(l.kind);
        }
    }
    let mut spans = vec![Span::raw(" ")];
    for kind in kinds {
        let (symbol, color) = landmark_symbol(kind);
        spans.push(Span::styled(
            format!("{symbol}{kind} "),
            Style::new().fg(color),
        ));
    }
    for mode in [
        DroneMode::Idle,
        DroneMode::Flying,
        DroneMode::Tracking,
        DroneMode::Unavailable,
    ] {
        spans.push(Span::styled(
            format!("{DRONE_MARKER}{} ", short_mode(mode)),
            Style::new().fg(mode_color(mode)),
        ));
    }
    Line::from(spans)
}
