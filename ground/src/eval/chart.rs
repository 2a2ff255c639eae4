//! The evaluation chart, laid out like the paper's figure: the success rate (with its 95 %
//! Wilson interval) and the mean number of Supervisor cycles L over successful runs, grouped by
//! swarm size with one bar per mode. SVG written by hand, as `plot` does.

use super::results::Cell;
use std::fmt::Write;

const PANEL_W: f64 = 420.0;
const PANEL_H: f64 = 300.0;
const LEFT: f64 = 55.0;
const TOP: f64 = 50.0;
const BOTTOM: f64 = 45.0;
const GAP: f64 = 70.0;

fn colour(i: usize) -> &'static str {
    ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b"][i % 5]
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// What one panel shows for a cell: the bar's height, and an error bar when there is one.
type Value = fn(&Cell) -> Option<(f64, Option<(f64, f64)>)>;

#[allow(clippy::too_many_arguments)]
fn panel(
    out: &mut String,
    x0: f64,
    title: &str,
    max: f64,
    ticks: &[f64],
    tick_label: fn(f64) -> String,
    cells: &[Cell],
    modes: &[String],
    sizes: &[usize],
    value: Value,
) {
    let plot_h = PANEL_H - BOTTOM;
    let y = |v: f64| TOP + plot_h * (1.0 - (v / max).clamp(0.0, 1.0));
    let _ = writeln!(
        out,
        r#"<text x="{:.1}" y="{:.1}" font-size="14" text-anchor="middle">{}</text>"#,
        x0 + PANEL_W / 2.0,
        TOP - 20.0,
        escape(title)
    );
    for t in ticks {
        let _ = writeln!(
            out,
            r##"<line x1="{x0:.1}" y1="{yy:.1}" x2="{x1:.1}" y2="{yy:.1}" stroke="#ddd"/><text x="{tx:.1}" y="{ty:.1}" font-size="11" text-anchor="end">{label}</text>"##,
            yy = y(*t),
            x1 = x0 + PANEL_W,
            tx = x0 - 6.0,
            ty = y(*t) + 4.0,
            label = tick_label(*t)
        );
    }
    let _ = writeln!(
        out,
        r#"<line x1="{x0:.1}" y1="{b:.1}" x2="{x1:.1}" y2="{b:.1}" stroke="black"/><line x1="{x0:.1}" y1="{TOP:.1}" x2="{x0:.1}" y2="{b:.1}" stroke="black"/>"#,
        b = TOP + plot_h,
        x1 = x0 + PANEL_W
    );
    let group_w = PANEL_W / sizes.len().max(1) as f64;
    let bar_w = (group_w * 0.75) / modes.len().max(1) as f64;
    for (g, size) in sizes.iter().enumerate() {
        let gx = x0 + g as f64 * group_w + group_w * 0.125;
        let _ = writeln!(
            out,
            r#"<text x="{:.1}" y="{:.1}" font-size="12" text-anchor="middle">{size} drones</text>"#,
            x0 + (g as f64 + 0.5) * group_w,
            TOP + plot_h + 18.0
        );
        for (m, mode) in modes.iter().enumerate() {
            let Some(cell) = cells.iter().find(|c| c.drones == *size && &c.mode == mode) else {
                continue;
            };
            let bx = gx + m as f64 * bar_w;
            match value(cell) {
                Some((v, err)) => {
                    let _ = writeln!(
                        out,
                        r#"<rect x="{bx:.1}" y="{top:.1}" width="{w:.1}" height="{h:.1}" fill="{fill}"><title>{mode}, {size} drones: {v:.2} ({n} runs)</title></rect>"#,
                        top = y(v),
                        w = bar_w * 0.9,
                        h = (TOP + plot_h - y(v)).max(0.0),
                        fill = colour(m),
                        mode = escape(mode),
                        n = cell.runs
                    );
                    if let Some((lo, hi)) = err {
                        let cx = bx + bar_w * 0.45;
                        let _ = writeln!(
                            out,
                            r#"<path d="M{cx:.1},{a:.1}V{b:.1}M{l:.1},{a:.1}H{r:.1}M{l:.1},{b:.1}H{r:.1}" stroke="black" fill="none"/>"#,
                            a = y(hi),
                            b = y(lo),
                            l = cx - 4.0,
                            r = cx + 4.0
                        );
                    }
                }
                // No value (no successful run for L): say so instead of drawing a zero.
                None => {
                    let _ = writeln!(
                        out,
                        r#"<text x="{:.1}" y="{:.1}" font-size="10" text-anchor="middle">n/a</text>"#,
                        bx + bar_w * 0.45,
                        TOP + plot_h - 4.0
                    );
                }
            }
        }
    }
}

/// The chart for `cells` (one per mode and swarm size).
pub fn svg(title: &str, cells: &[Cell], modes: &[String]) -> String {
    let mut sizes: Vec<usize> = cells.iter().map(|c| c.drones).collect();
    sizes.sort_unstable();
    sizes.dedup();
    let width = LEFT + 2.0 * PANEL_W + GAP + 20.0;
    let height = TOP + PANEL_H + 50.0;
    let mut out = String::new();
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0}" height="{height:.0}" viewBox="0 0 {width:.0} {height:.0}" font-family="sans-serif">"#
    );
    let _ = writeln!(
        out,
        r#"<rect width="100%" height="100%" fill="white"/><text x="{:.1}" y="18" font-size="15" text-anchor="middle" font-weight="bold">{}</text>"#,
        width / 2.0,
        escape(title)
    );
    panel(
        &mut out,
        LEFT,
        "Success rate (95 % Wilson interval)",
        1.0,
        &[0.0, 0.25, 0.5, 0.75, 1.0],
        |t| format!("{:.0} %", 100.0 * t),
        cells,
        modes,
        &sizes,
        |c| (c.runs > 0).then_some((c.rate, Some(c.interval))),
    );
    let max_l = cells
        .iter()
        .filter_map(|c| c.mean_cycles)
        .fold(1.0_f64, f64::max)
        .ceil()
        .max(1.0);
    let step = (max_l / 5.0).ceil().max(1.0);
    let ticks: Vec<f64> = (0..=((max_l / step).ceil() as usize))
        .map(|i| i as f64 * step)
        .collect();
    let top_tick = ticks.last().copied().unwrap_or(max_l).max(max_l);
    panel(
        &mut out,
        LEFT + PANEL_W + GAP,
        "Mean Supervisor cycles L (successful runs)",
        top_tick,
        &ticks,
        |t| format!("{t:.0}"),
        cells,
        modes,
        &sizes,
        |c| c.mean_cycles.map(|l| (l, None)),
    );
    for (m, mode) in modes.iter().enumerate() {
        let x = LEFT + m as f64 * 110.0;
        let y = TOP + PANEL_H + 30.0;
        let _ = writeln!(
            out,
            r#"<rect x="{x:.1}" y="{:.1}" width="12" height="12" fill="{}"/><text x="{:.1}" y="{y:.1}" font-size="12">{}</text>"#,
            y - 10.0,
            colour(m),
            x + 16.0,
            escape(mode)
        );
    }
    out.push_str("</svg>\n");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(mode: &str, drones: usize, successes: u32, l: Option<f64>) -> Cell {
        Cell {
            mode: mode.into(),
            drones,
            runs: 2,
            successes,
            errors: 0,
            rate: f64::from(successes) / 2.0,
            interval: super::super::results::wilson_interval(successes, 2),
            mean_cycles: l,
            mean_model_calls: 3.0,
            mean_latency_s: Some(1.0),
            mean_tokens: 10.0,
            mean_wall_s: 20.0,
            mean_mission_s: Some(30.0),
        }
    }

    #[test]
    fn the_chart_has_a_bar_per_cell_and_marks_missing_l() {
        let modes = vec!["tacos".to_owned(), "mnl".to_owned()];
        let cells = vec![
            cell("tacos", 6, 2, Some(4.5)),
            cell("mnl", 6, 0, None),
            cell("tacos", 12, 1, Some(6.0)),
        ];
        let svg = svg("find-suspect <model>", &cells, &modes);
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert!(svg.contains("find-suspect &lt;model&gt;"));
        // Three success-rate bars (mnl at 0 % is a bar of height 0) and two L bars.
        assert_eq!(svg.matches("<rect x=").count() - modes.len(), 5, "{svg}");
        assert_eq!(svg.matches(">n/a<").count(), 1);
        assert!(svg.contains("tacos, 6 drones: 4.50"));
    }
}
