//! The panes, one render function each, and the layout that places them.
//!
//! Every function draws from a `&TerminalState` into a buffer and nothing else, so each pane can
//! be rendered on ratatui's `TestBackend` and compared with an expected screen.

use super::state::{ChatEntry, DroneRow, EventKind, Focus, TerminalState};
use ratatui::Frame;
use ratatui::buffer::Buffer;
use ratatui::layout::{Constraint, Layout, Position, Rect};
use ratatui::style::{Color, Modifier, Style};
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::canvas::{Canvas, Context, Line as CanvasLine, Points, Rectangle};
use ratatui::widgets::{Block, Cell, Paragraph, Row, Table, Widget};
use tacos_shared::DroneMode;
use tacos_shared::messages::{ActionState, FailsafeStage};
use tacos_shared::world::{Ellipsoid, LandmarkKind};

/// Where each pane goes; a pane that does not fit is `None`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Areas {
    pub map: Option<Rect>,
    pub chat: Option<Rect>,
    pub events: Option<Rect>,
    pub swarm: Option<Rect>,
    pub status: Option<Rect>,
    pub input: Rect,
}

/// Places the panes. At 100×24 and more: map on the left, chat over the event log on the
/// right, the swarm table across (at most a third of the height; it scrolls), the status bar
/// and the input line. Smaller: the map goes first, then the event log, then the table.
pub fn layout(area: Rect, drones: usize) -> Areas {
    let mut areas = Areas {
        map: None,
        chat: None,
        events: None,
        swarm: None,
        status: None,
        input: area,
    };
    if area.height < 5 {
        // Only the input line is left.
        areas.input = Rect {
            y: area.y + area.height.saturating_sub(1),
            height: area.height.min(1),
            ..area
        };
        return areas;
    }
    let [body, status, input] = Layout::vertical([
        Constraint::Fill(1),
        Constraint::Length(1),
        Constraint::Length(3),
    ])
    .areas(area);
    areas.status = Some(status);
    areas.input = input;
    if body.height < 6 {
        areas.chat = (body.height > 0).then_some(body);
        return areas;
    }
    let table_rows = (drones as u16 + 3).min((area.height / 3).max(4));
    let [top, swarm] =
        Layout::vertical([Constraint::Fill(1), Constraint::Length(table_rows)]).areas(body);
    areas.swarm = Some(swarm);
    let full = area.width >= 100 && area.height >= 24;
    let right = if full {
        // About square in metres for a square world: a cell is twice as tall as wide.
        let map_width = (area.width / 2).min(top.height.saturating_sub(2) * 2 + 2);
        let [map, right] =
            Layout::horizontal([Constraint::Length(map_width), Constraint::Fill(1)]).areas(top);
        areas.map = Some(map);
        right
    } else {
        top
    };
    if right.width >= 60 || full {
        let [chat, events] =
            Layout::vertical([Constraint::Percentage(60), Constraint::Percentage(40)]).areas(right);
        areas.chat = Some(chat);
        areas.events = Some(events);
    } else if right.height >= 10 {
        let [chat, events] =
            Layout::vertical([Constraint::Percentage(65), Constraint::Percentage(35)]).areas(right);
        areas.chat = Some(chat);
        areas.events = Some(events);
    } else {
        areas.chat = Some(right);
    }
    areas
}

/// Draws every pane and puts the cursor in the input line.
pub fn draw(frame: &mut Frame, state: &TerminalState) {
    let area = frame.area();
    let areas = layout(area, state.drones.len());
    let buf = frame.buffer_mut();
    if let Some(a) = areas.map {
        render_map(state, a, buf);
    }
    if let Some(a) = areas.chat {
        render_chat(state, a, buf);
    }
    if let Some(a) = areas.events {
        render_events(state, a, buf);
    }
    if let Some(a) = areas.swarm {
        render_swarm(state, a, buf);
    }
    if let Some(a) = areas.status {
        render_status(state, a, buf);
    }
    render_input(state, areas.input, buf);
    if let Some(p) = input_cursor(state, areas.input) {
        frame.set_cursor_position(p);
    }
}

// ---- colours and symbols -----------------------------------------------------------------------

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

fn pane(title: impl Into<String>, focused: bool) -> Block<'static> {
    let border = if focused {
        Color::Yellow
    } else {
        Color::DarkGray
    };
    Block::bordered()
        .border_style(Style::new().fg(border))
        .title(Span::styled(
            format!(" {} ", title.into()),
            Style::new().add_modifier(Modifier::BOLD),
        ))
}

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

fn short_mode(mode: DroneMode) -> &'static str {
    match mode {
        DroneMode::Unavailable => "unav",
        DroneMode::Idle => "idle",
        DroneMode::Flying => "fly",
        DroneMode::Tracking => "track",
    }
}

// ---- swarm table ---------------------------------------------------------------------------

fn state_text(row: &DroneRow) -> (String, Color) {
    let (mut text, color) = match &row.state {
        Some(ActionState::Running { progress }) => {
            (format!("running {:>3.0}%", progress * 100.0), Color::Yellow)
        }
        Some(ActionState::Done) => ("done".to_owned(), Color::Green),
        Some(ActionState::Failed(why)) => (format!("failed: {why}"), Color::Red),
        None => ("-".to_owned(), Color::DarkGray),
    };
    match row.failsafe {
        Some(FailsafeStage::Holding) => text.push_str(" [failsafe hold]"),
        Some(FailsafeStage::Landing) => text.push_str(" [failsafe land]"),
        None => {}
    }
    (text, color)
}

fn link_text(row: &DroneRow) -> (String, Color) {
    match (row.alive, row.link_age) {
        (false, Some(_)) => ("gone".to_owned(), Color::Red),
        (_, None) => ("no data".to_owned(), Color::DarkGray),
        (true, Some(age)) if age > crate::swarm::STALE_AFTER_S => {
            (format!("{age:.1} s"), Color::Red)
        }
        (true, Some(age)) => (format!("{:.0} ms", age * 1000.0), Color::Gray),
    }
}

/// The first row the table shows, given the scroll offset and how many rows fit.
pub fn swarm_first_row(state: &TerminalState, visible: usize) -> usize {
    state
        .scroll
        .swarm
        .min(state.drones.len().saturating_sub(visible))
}

/// One row per drone: name, mode, position, speed, task/action, state, link age.
pub fn render_swarm(state: &TerminalState, area: Rect, buf: &mut Buffer) {
    let visible = usize::from(area.height.saturating_sub(3));
    let first = swarm_first_row(state, visible);
    let shown = state.drones.len().min(visible);
    let mut title = format!(
        "swarm · {} drones, {} airborne",
        state.drones.len(),
        state.airborne()
    );
    if shown < state.drones.len() {
        title.push_str(&format!(
            " · rows {}–{} of {}",
            first + 1,
            first + shown,
            state.drones.len()
        ));
    }
    let header = Row::new(
        [
            "DRONE",
            "MODE",
            "POSITION x, y, z (m)",
            "SPEED",
            "TASK / ACTION",
            "STATE",
            "LINK",
        ]
        .map(Cell::from),
    )
    .style(Style::new().add_modifier(Modifier::BOLD));
    let rows = state.drones.iter().skip(first).take(visible).map(|d| {
        let mode = Style::new().fg(mode_color(d.mode));
        let position = d
            .position
            .map(|p| format!("({:>6.1}, {:>6.1}, {:>5.1})", p.x, p.y, p.z))
            .unwrap_or_else(|| "-".into());
        let speed = d
            .speed()
            .map(|s| format!("{s:>5.1}"))
            .unwrap_or_else(|| "    -".into());
        let action = match (&d.task, &d.action) {
            (Some(t), Some(a)) => format!("{t}: {a}"),
            (None, Some(a)) => a.clone(),
            _ => "-".into(),
        };
        let (state_text, state_color) = state_text(d);
        let (link, link_color) = link_text(d);
        Row::new(vec![
            Cell::from(d.id.clone()).style(mode.add_modifier(Modifier::BOLD)),
            Cell::from(d.mode.as_str()).style(mode),
            Cell::from(position),
            Cell::from(speed),
            Cell::from(action),
            Cell::from(state_text).style(Style::new().fg(state_color)),
            Cell::from(format!("{link:>7}")).style(Style::new().fg(link_color)),
        ])
    });
    let table = Table::new(
        rows,
        [
            Constraint::Length(9),
            Constraint::Length(11),
            Constraint::Length(23),
            Constraint::Length(5),
            Constraint::Fill(1),
            Constraint::Fill(1),
            Constraint::Length(7),
        ],
    )
    .header(header)
    .block(pane(title, state.focus == Focus::Swarm));
    Widget::render(table, area, buf);
}

// ---- chat and event log --------------------------------------------------------------------

/// Greedy word wrap to `width` columns; words longer than a line are cut.
pub fn wrap(text: &str, width: usize) -> Vec<String> {
    let width = width.max(1);
    let mut lines = Vec::new();
    for paragraph in text.split('\n') {
        let mut line = String::new();
        let mut used = 0;
        for word in paragraph.split_whitespace() {
            let mut word: Vec<char> = word.chars().collect();
            loop {
                let len = Span::raw(word.iter().collect::<String>()).width();
                let gap = usize::from(used > 0);
                if used + gap + len <= width {
                    if gap == 1 {
                        line.push(' ');
                    }
                    line.extend(word.iter());
                    used += gap + len;
                    break;
                }
                if used > 0 {
                    lines.push(std::mem::take(&mut line));
                    used = 0;
                    continue;
                }
                // A word wider than the line: cut it.
                let cut = word.len().min(width);
                let head: String = word.drain(..cut).collect();
                lines.push(head);
                if word.is_empty() {
                    break;
                }
            }
        }
        lines.push(line);
    }
    lines
}

/// A prefixed, wrapped paragraph: the first line starts with `prefix`, the rest are indented to
/// its width.
fn paragraph_lines(
    out: &mut Vec<Line<'static>>,
    prefix: &str,
    prefix_style: Style,
    text: &str,
    text_style: Style,
    width: usize,
) {
    let indent = Span::raw(prefix).width();
    let body = width.saturating_sub(indent).max(1);
    for (i, chunk) in wrap(text, body).into_iter().enumerate() {
        let lead = if i == 0 {
            Span::styled(prefix.to_owned(), prefix_style)
        } else {
            Span::raw(" ".repeat(indent))
        };
        out.push(Line::from(vec![lead, Span::styled(chunk, text_style)]));
    }
}

/// The chat as wrapped lines for an inner width.
pub fn chat_lines(state: &TerminalState, width: usize) -> Vec<Line<'static>> {
    let mut out = Vec::new();
    let bold = |c: Color| Style::new().fg(c).add_modifier(Modifier::BOLD);
    for entry in &state.chat {
        match entry {
            ChatEntry::Pilot(text) => paragraph_lines(
                &mut out,
                "pilot › ",
                bold(Color::Cyan),
                text,
                Style::new(),
                width,
            ),
            ChatEntry::Coordinator { reasoning, calls } => {
                paragraph_lines(
                    &mut out,
                    "coordinator › ",
                    bold(Color::Magenta),
                    reasoning,
                    Style::new(),
                    width,
                );
                if calls.is_empty() {
                    paragraph_lines(
                        &mut out,
                        "  plan: ",
                        Style::new().fg(Color::Magenta),
                        "(empty)",
                        Style::new().fg(Color::DarkGray),
                        width,
                    );
                }
                for (i, call) in calls.iter().enumerate() {
                    paragraph_lines(
                        &mut out,
                        &format!("  {:>2}. ", i + 1),
                        Style::new().fg(Color::Magenta),
                        call,
                        Style::new().fg(Color::Yellow),
                        width,
                    );
                }
            }
            ChatEntry::Supervisor {
                cycle,
                reasoning,
                actions,
            } => {
                paragraph_lines(
                    &mut out,
                    &format!("supervisor #{cycle} › "),
                    bold(Color::Blue),
                    reasoning,
                    Style::new(),
                    width,
                );
                if actions.is_empty() {
                    paragraph_lines(
                        &mut out,
                        "  → ",
                        Style::new().fg(Color::Blue),
                        "no action this cycle",
                        Style::new().fg(Color::DarkGray),
                        width,
                    );
                }
                for action in actions {
                    paragraph_lines(
                        &mut out,
                        "  → ",
                        Style::new().fg(Color::Blue),
                        action,
                        Style::new().fg(Color::Green),
                        width,
                    );
                }
            }
            ChatEntry::PlanComplete { cycles } => paragraph_lines(
                &mut out,
                "✓ ",
                bold(Color::Green),
                &format!("plan complete after {cycles} supervisor cycles"),
                Style::new().fg(Color::Green),
                width,
            ),
            ChatEntry::Error(text) => paragraph_lines(
                &mut out,
                "✗ ",
                bold(Color::Red),
                text,
                Style::new().fg(Color::Red),
                width,
            ),
        }
    }
    out
}

/// Renders the lines that fit, `back` lines up from the end (clamped); a scrolled view says how
/// many lines are below it.
fn render_tail(
    lines: Vec<Line<'static>>,
    back: usize,
    block: Block<'static>,
    area: Rect,
    buf: &mut Buffer,
) {
    let inner = block.inner(area);
    let height = usize::from(inner.height);
    let back = back.min(lines.len().saturating_sub(height));
    let end = lines.len() - back;
    let start = end.saturating_sub(height);
    let block = if back > 0 {
        block.title_bottom(Line::styled(
            format!(" ↓ {back} more lines "),
            Style::new().fg(Color::Yellow),
        ))
    } else {
        block
    };
    let shown: Vec<Line<'static>> = lines.into_iter().skip(start).take(end - start).collect();
    Paragraph::new(shown).block(block).render(area, buf);
}

/// The pilot's lines, the Coordinator's reasoning and plan, the Supervisor's cycles.
pub fn render_chat(state: &TerminalState, area: Rect, buf: &mut Buffer) {
    let block = pane("chat", state.focus == Focus::Chat);
    let width = usize::from(block.inner(area).width);
    render_tail(
        chat_lines(state, width),
        state.scroll.chat,
        block,
        area,
        buf,
    );
}

pub fn event_color(kind: EventKind) -> Color {
    match kind {
        EventKind::Failure | EventKind::Error => Color::Red,
        EventKind::Replan => Color::LightYellow,
        EventKind::Rejected => Color::LightRed,
        EventKind::Detection => Color::LightMagenta,
        EventKind::Direct => Color::LightCyan,
        EventKind::Sent => Color::Gray,
        EventKind::Done => Color::Green,
        EventKind::Info => Color::White,
    }
}

/// The event log as wrapped lines.
pub fn event_lines(state: &TerminalState, width: usize) -> Vec<Line<'static>> {
    let mut out = Vec::new();
    for e in &state.events {
        paragraph_lines(
            &mut out,
            &format!("{:>6.1}s ", e.at.as_secs_f64()),
            Style::new().fg(Color::DarkGray),
            &e.text,
            Style::new().fg(event_color(e.kind)),
            width,
        );
    }
    out
}

/// Failures, replans, gate rejections, detections, direct commands, sends and outcomes.
pub fn render_events(state: &TerminalState, area: Rect, buf: &mut Buffer) {
    let block = pane("events", state.focus == Focus::Events);
    let width = usize::from(block.inner(area).width);
    render_tail(
        event_lines(state, width),
        state.scroll.events,
        block,
        area,
        buf,
    );
}

// ---- status bar and input ------------------------------------------------------------------

const SPINNER: [char; 10] = ['⠋', '⠙', '⠹', '⠸', '⠼', '⠴', '⠦', '⠧', '⠇', '⠏'];

/// The status line: scenario, backend, the last call, and the call in flight.
pub fn status_line(state: &TerminalState) -> Line<'static> {
    let bar = Style::new().bg(Color::DarkGray).fg(Color::White);
    let mut spans = vec![Span::styled(
        " TACOS ",
        Style::new()
            .bg(Color::Cyan)
            .fg(Color::Black)
            .add_modifier(Modifier::BOLD),
    )];
    // What matters most first: a narrow bar cuts the backend's description, not the timer.
    match state.thinking_for() {
        Some((layer, secs)) => {
            let frame = SPINNER[(secs * 10.0) as usize % SPINNER.len()];
            spans.push(Span::styled(
                format!(" {frame} {layer} thinking… {secs:.1} s "),
                bar.fg(Color::Yellow).add_modifier(Modifier::BOLD),
            ));
        }
        None => spans.push(Span::styled(" ready ".to_owned(), bar.fg(Color::Green))),
    }
    if state.status.confirm {
        spans.push(Span::styled(
            "│ confirm (F2) ".to_owned(),
            bar.fg(Color::Magenta).add_modifier(Modifier::BOLD),
        ));
    }
    if let Some(call) = &state.status.last_call {
        spans.push(Span::styled(
            format!(
                "│ last: {} {:.1} s, {}+{} tok ",
                call.layer,
                call.latency.as_secs_f64(),
                call.prompt_tokens,
                call.completion_tokens,
            ),
            bar,
        ));
    }
    spans.push(Span::styled(
        format!("│ {} · {} ", state.scenario_name, state.status.backend),
        bar,
    ));
    Line::from(spans)
}

pub fn render_status(state: &TerminalState, area: Rect, buf: &mut Buffer) {
    buf.set_style(area, Style::new().bg(Color::DarkGray));
    Paragraph::new(status_line(state)).render(area, buf);
}

const PROMPT: &str = "› ";

/// The first character of the input shown, so that the cursor stays visible.
fn input_window(state: &TerminalState, width: usize) -> usize {
    let room = width.saturating_sub(PROMPT.chars().count() + 1).max(1);
    state.input.cursor().saturating_sub(room)
}

fn input_inner(area: Rect) -> Rect {
    if area.height >= 3 {
        Block::bordered().inner(area)
    } else {
        area
    }
}

/// The pilot's line, with keys in the border.
pub fn render_input(state: &TerminalState, area: Rect, buf: &mut Buffer) {
    let inner = input_inner(area);
    let start = input_window(state, usize::from(inner.width));
    let text: String = state.input.text().chars().skip(start).collect();
    let line = Line::from(vec![
        Span::styled(
            PROMPT,
            Style::new().fg(Color::Cyan).add_modifier(Modifier::BOLD),
        ),
        Span::raw(text),
    ]);
    let paragraph = Paragraph::new(line);
    if area.height >= 3 {
        let block = pane("pilot", false).title_bottom(Line::styled(
            " Enter send · ↑↓ history · Tab focus · PgUp/PgDn scroll · Esc quit ",
            Style::new().fg(Color::DarkGray),
        ));
        paragraph.block(block).render(area, buf);
    } else {
        paragraph.render(area, buf);
    }
}

/// Where the terminal's cursor goes in the input line.
pub fn input_cursor(state: &TerminalState, area: Rect) -> Option<Position> {
    let inner = input_inner(area);
    if inner.width == 0 || inner.height == 0 {
        return None;
    }
    let start = input_window(state, usize::from(inner.width));
    let before: String = state
        .input
        .text()
        .chars()
        .skip(start)
        .take(state.input.cursor() - start)
        .collect();
    let x = Span::raw(format!("{PROMPT}{before}")).width() as u16;
    Some(Position::new(
        inner.x + x.min(inner.width.saturating_sub(1)),
        inner.y,
    ))
}
