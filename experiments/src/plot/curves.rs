//! Learning curves (the paper's Figure 4): return per episode for each method, the mean over
//! seeds as a line and ± one standard deviation as a shaded band.

use super::{Figure, XAxis, chart, color, padded_range, plot_err};
use crate::results::Curve;
use anyhow::Result;
use plotters::coord::Shift;
use plotters::prelude::*;

/// The learning curves of one task.
pub struct LearningCurves {
    pub title: String,
    pub curves: Vec<Curve>,
}

impl Figure for LearningCurves {
    fn size(&self) -> (u32, u32) {
        (800, 520)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, text: bool) -> Result<()> {
        let points = self.curves.iter().flat_map(|c| &c.points);
        let episodes = padded_range(points.clone().map(|p| f64::from(p.episode)));
        let returns = padded_range(points.flat_map(|p| [p.mean - p.std, p.mean + p.std]));
        let mut chart = chart(
            root,
            &self.title,
            ((episodes.0.min(0.0), episodes.1), XAxis::Steps),
            returns,
            ("episode", "return"),
            text,
        )?;
        for (i, curve) in self.curves.iter().enumerate() {
            let c = color(i);
            let upper = curve
                .points
                .iter()
                .map(|p| (f64::from(p.episode), p.mean + p.std));
            let lower = curve
                .points
                .iter()
                .rev()
                .map(|p| (f64::from(p.episode), p.mean - p.std));
            chart
                .draw_series(std::iter::once(Polygon::new(
                    upper.chain(lower).collect::<Vec<_>>(),
                    c.mix(0.18).filled(),
                )))
                .map_err(plot_err)?;
            let line = curve.points.iter().map(|p| (f64::from(p.episode), p.mean));
            let series = chart
                .draw_series(LineSeries::new(line.clone(), c.stroke_width(2)))
                .map_err(plot_err)?;
            if text {
                let seeds = curve.points.iter().map(|p| p.seeds).max().unwrap_or(0);
                series
                    .label(legend_label(&curve.method, seeds))
                    .legend(move |(x, y)| {
                        PathElement::new([(x, y), (x + 20, y)], c.stroke_width(2))
                    });
            }
            chart
                .draw_series(line.map(|xy| Circle::new(xy, 3, c.filled())))
                .map_err(plot_err)?;
        }
        if text {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK.mix(0.4))
                .label_font((super::FAMILY, 14))
                .draw()
                .map_err(plot_err)?;
        }
        Ok(())
    }
}

/// A curve's legend entry: the method and how many seeds its widest point averages.
fn legend_label(method: &str, seeds: usize) -> String {
    let noun = if seeds == 1 { "seed" } else { "seeds" };
    format!("{method} ({seeds} {noun})")
}

#[cfg(test)]
mod tests {
    use super::legend_label;

    #[test]
    fn legend_counts_seeds_in_words() {
        assert_eq!(legend_label("adam+dae", 1), "adam+dae (1 seed)");
        assert_eq!(legend_label("cem+deen", 6), "cem+deen (6 seeds)");
    }
}
