//! The panes, one render function each, and the layout that places them.
//!
//! Every function draws from a `&TerminalState` into a buffer and nothing else, so each pane can
//! be rendered on ratatui's `TestBackend` and compared with an expected screen.

use super::chat::paragraph_lines;
pub use super::chat::{chat_lines, wrap};
pub use super::map::{
    DRONE_MARKER, TARGET_MARKER, ellipse_footprint, landmark_symbol, map_bounds, mode_color,
    render_map,
};
use super::state::{DroneRow, EventKind, Focus, TerminalState};
use crate::status_marks::status_marks;
use ratatui::Frame;
use ratatui::buffer::Buffer;
use ratatui::layout::{Constraint, Layout, Position, Rect};
use ratatui::style::{Color, Modifier, Style};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Block, Cell, Paragraph, Row, Table, Widget};
use tacos_shared::DroneMode;
use tacos_shared::messages::ActionState;

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

pub(super) fn pane(title: impl Into<String>, focused: bool) -> Block<'static> {
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

pub(super) fn short_mode(mode: DroneMode) -> &'static str {
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
    text.push_str(&status_marks(
        row.failsafe,
        row.peers_silent,
        row.autopilot_took_over,
    ));
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
