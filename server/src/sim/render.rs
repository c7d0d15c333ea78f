//! The restaurant as text for humans (the `ansi` render mode): tables, queue, counters, hands,
//! score and lives.

use std::fmt::Write;

use super::restaurant::{NUM_TABLES, Restaurant, TABLE_CAPACITIES, status};

const STATUS_NAMES: [&str; 7] = [
    "free",
    "reading",
    "ready to order",
    "waiting for food",
    "eating",
    "dishes",
    "wants the bill",
];
/// ANSI colour per table status: calm when nothing is asked of the waiter, loud when something is.
const STATUS_COLORS: [&str; 7] = ["2", "36", "1;33", "33", "32", "35", "1;31"];

fn item_name(item: u8) -> String {
    match item {
        0 => "-".to_string(),
        1..=6 => format!("order(T{item})"),
        7..=12 => format!("food(T{})", item - 6),
        _ => format!("dish(T{})", item - 12),
    }
}

fn patience_bar(patience: i32, full: i32) -> String {
    let filled = ((patience.max(0) * 10 + full - 1) / full.max(1)).clamp(0, 10) as usize;
    format!(
        "[{}{}] {patience:>3}",
        "#".repeat(filled),
        ".".repeat(10 - filled)
    )
}

/// Draws the restaurant; with `color`, with ANSI colour codes.
pub fn render(r: &Restaurant, color: bool) -> String {
    let paint = |code: &str, text: &str| {
        if color {
            format!("\x1b[{code}m{text}\x1b[0m")
        } else {
            text.to_string()
        }
    };
    let config = r.config();
    let full = |customer_type: u8| config.patience[usize::from(customer_type - 1)] as i32;
    let mut out = String::new();
    let lives_left = config.lives.saturating_sub(r.lost());
    let _ = writeln!(
        out,
        "Diner Dash  tick {:>5}  score {:>6}  lives {}{}",
        r.tick(),
        r.score(),
        paint("1;31", &"♥".repeat(lives_left.min(20) as usize)),
        "♡".repeat(r.lost().min(config.lives).min(20) as usize),
    );
    for t in 1..=NUM_TABLES {
        let s = r.table_status(t);
        let mut line = format!(
            "  T{t} ({} seats) {}",
            TABLE_CAPACITIES[t - 1],
            paint(
                STATUS_COLORS[usize::from(s)],
                &format!("{:<16}", STATUS_NAMES[usize::from(s)])
            )
        );
        if let Some(g) = r.seated_group(t) {
            let _ = write!(
                line,
                " group of {} (type {}) {}",
                g.size,
                g.customer_type,
                patience_bar(g.patience, full(g.customer_type))
            );
        } else if s == status::DISHES {
            line.push_str(" dishes to clear");
        }
        let _ = writeln!(out, "{line}");
    }
    let counters: Vec<String> = r
        .counters()
        .iter()
        .map(|&c| {
            if c == 0 {
                "-".into()
            } else {
                format!("food(T{c})")
            }
        })
        .collect();
    let _ = writeln!(out, "  counters: {}", counters.join(" "));
    let hands: Vec<String> = r.hands().iter().map(|&i| item_name(i)).collect();
    let _ = writeln!(out, "  hands:    {}", hands.join(" "));
    let _ = writeln!(out, "  queue ({}/7):", r.queue().len());
    for (g, group) in r.queue().iter().enumerate() {
        let _ = writeln!(
            out,
            "    {}. group of {} (type {}) {}",
            g + 1,
            group.size,
            group.customer_type,
            patience_bar(group.patience, full(group.customer_type))
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Config, Game};

    #[test]
    fn shows_tables_queue_and_score() {
        let mut g = Game::new(Config::default()).unwrap();
        g.reset(Some(100), None).unwrap();
        g.step(15).unwrap();
        let text = render(g.restaurant(), false);
        assert!(text.contains("score     10"), "{text}");
        assert!(text.contains("T1 (4 seats) reading"), "{text}");
        assert!(text.contains("queue (0/7)"), "{text}");
        assert!(!text.contains('\x1b'));
        assert!(render(g.restaurant(), true).contains('\x1b'));
    }
}
