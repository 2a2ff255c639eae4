//! The chat pane's text: the pilot's lines, the Coordinator's reasoning and plans, the
//! Supervisor's cycles, and a reply still being written; and the word wrap the panes share.

use super::state::{ChatEntry, TerminalState, Writing};
use ratatui::style::{Color, Modifier, Style};
use ratatui::text::{Line, Span};

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
pub(super) fn paragraph_lines(
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
    if let Some(writing) = &state.writing {
        writing_lines(&mut out, writing, width);
    }
    out
}

/// A reply still being written: its reasoning and its complete calls so far, dimmed.
fn writing_lines(out: &mut Vec<Line<'static>>, writing: &Writing, width: usize) {
    let dim = Style::new().fg(Color::DarkGray);
    let reasoning = if writing.reasoning.is_empty() {
        "…"
    } else {
        writing.reasoning.as_str()
    };
    paragraph_lines(
        out,
        &format!("{} (writing) › ", writing.layer),
        dim.add_modifier(Modifier::BOLD),
        reasoning,
        dim.add_modifier(Modifier::ITALIC),
        width,
    );
    for call in &writing.calls {
        paragraph_lines(out, "   · ", dim, call, dim, width);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mission::MissionUpdate;
    use std::time::{Duration, Instant};
    use tacos_shared::scenario::Scenario;

    fn text(lines: &[Line<'static>]) -> Vec<String> {
        lines
            .iter()
            .map(|l| l.spans.iter().map(|s| s.content.as_ref()).collect())
            .collect()
    }

    /// A reply being written shows below the chat, grows with each update, and gives way to the
    /// plan once it is in.
    #[test]
    fn a_reply_being_written_shows_until_it_is_in() {
        let t0 = Instant::now();
        let lab = Scenario::builtin("lab").expect("the lab scenario is built in");
        let mut state = TerminalState::new(&lab, "test", t0);
        state.apply_update(
            &MissionUpdate::Thinking {
                layer: "coordinator",
            },
            t0,
        );
        let writing = |reasoning: &str, calls: &[&str]| MissionUpdate::Writing {
            layer: "coordinator",
            reasoning: reasoning.into(),
            calls: calls.iter().map(|c| (*c).to_owned()).collect(),
        };
        state.apply_update(&writing("Alfa is clo", &[]), t0);
        assert_eq!(
            text(&chat_lines(&state, 60)),
            ["coordinator (writing) › Alfa is clo"]
        );
        let later = t0 + Duration::from_millis(300);
        state.apply_update(
            &writing("Alfa is closest.", &["T1 alfa goto(car_11)"]),
            later,
        );
        assert_eq!(
            text(&chat_lines(&state, 60)),
            [
                "coordinator (writing) › Alfa is closest.",
                "   · T1 alfa goto(car_11)"
            ]
        );
        assert!(
            state.thinking_for().is_some(),
            "still thinking while it writes"
        );
        let plan = MissionUpdate::Plan {
            reasoning: "Alfa is closest.".into(),
            calls: vec!["T1 alfa goto(car_11)".into()],
        };
        state.apply_update(&plan, later);
        let lines = text(&chat_lines(&state, 60));
        assert!(!lines.iter().any(|l| l.contains("writing")), "{lines:?}");
        assert_eq!(lines[0], "coordinator › Alfa is closest.");
    }
}
