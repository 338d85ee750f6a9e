//! Figures with plotters, written as PNG and SVG side by side.
//!
//! plotters is built without its `ttf` feature (that links fontconfig and freetype, which a clean
//! CI machine may lack); text goes through `ab_glyph` from a TTF file found at run time (see
//! [`fonts`]). Without one, figures are still drawn — axes, curves and bands, no text — and a
//! warning says so, because a figure without labels is more use than no figure.

pub mod curves;
pub mod fonts;

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};

/// The font family figures use (registered by [`fonts::ensure`]).
pub const FAMILY: &str = "sans-serif";

/// Series colours, in order (colour-blind-safe Okabe–Ito palette).
pub const PALETTE: [RGBColor; 7] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(0, 0, 0),
];

/// The colour of the `i`-th series.
pub fn color(i: usize) -> RGBColor {
    PALETTE[i % PALETTE.len()]
}

/// Something that draws itself on any plotters backend.
pub trait Figure {
    /// Pixel size of the figure.
    fn size(&self) -> (u32, u32);

    /// Draws on `root`; `text` says whether a font is available (no captions, labels or
    /// legends without one).
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, text: bool) -> Result<()>;
}

/// Turns a plotters error (whose type depends on the backend) into an `anyhow` error.
pub fn plot_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing failed: {e:?}")
}

/// Writes `figure` to `<stem>.png` and `<stem>.svg` and returns both paths. Draws text only
/// if `text` (normally [`fonts::ensure`]'s answer).
pub fn save<F: Figure>(figure: &F, stem: &Path, text: bool) -> Result<[PathBuf; 2]> {
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    if let Some(dir) = stem.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    {
        let root = BitMapBackend::new(&png, figure.size()).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        figure.draw(&root, text)?;
        root.present().map_err(plot_err)?;
    }
    {
        let root = SVGBackend::new(&svg, figure.size()).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        figure.draw(&root, text)?;
        root.present().map_err(plot_err)?;
    }
    Ok([png, svg])
}

/// `(min, max)` of `values` widened by 5 % each side (and to a unit range if flat), for axes.
pub fn padded_range(values: impl IntoIterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(v), h.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-9 {
        return (lo - 0.5, hi + 0.5);
    }
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

/// What the x axis counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum XAxis {
    /// A continuous quantity: ticks wherever plotters puts them.
    Continuous,
    /// Whole steps (episodes, plan steps): ticks only on integers.
    Steps,
}

/// A chart on `area` with `x`/`y` ranges; a caption and axis labels only when `text`.
pub fn chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    caption: &str,
    (x, x_axis): ((f64, f64), XAxis),
    y: (f64, f64),
    axes: (&str, &str),
    text: bool,
) -> Result<
    ChartContext<
        'a,
        DB,
        Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
    >,
> {
    let mut builder = ChartBuilder::on(area);
    builder.margin(12);
    if text {
        builder
            .caption(caption, (FAMILY, 18))
            .x_label_area_size(36)
            .y_label_area_size(56);
    } else {
        builder.x_label_area_size(8).y_label_area_size(8);
    }
    let mut chart = builder
        .build_cartesian_2d(x.0..x.1, y.0..y.1)
        .map_err(plot_err)?;
    let mut mesh = chart.configure_mesh();
    mesh.light_line_style(WHITE.mix(0.0));
    let integer_label = |v: &f64| {
        if (v - v.round()).abs() < 1e-6 {
            format!("{}", v.round() as i64)
        } else {
            String::new()
        }
    };
    if x_axis == XAxis::Steps {
        // At most one tick per step, and none between steps.
        let steps = (x.1.floor() - x.0.ceil()).max(0.0) as usize + 1;
        mesh.x_labels(steps.min(11))
            .x_label_formatter(&integer_label);
    }
    if text {
        mesh.x_desc(axes.0)
            .y_desc(axes.1)
            .label_style((FAMILY, 13))
            .axis_desc_style((FAMILY, 14));
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.draw().map_err(plot_err)?;
    Ok(chart)
}

/// Renders `figure` into an RGB pixel buffer (row-major, 3 bytes a pixel) without touching
/// the disk: what tests inspect.
pub fn render_rgb<F: Figure>(figure: &F, text: bool) -> Result<Vec<u8>> {
    let (w, h) = figure.size();
    let mut pixels = vec![0u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        figure.draw(&root, text)?;
        root.present().map_err(plot_err)?;
    }
    Ok(pixels)
}

#[cfg(test)]
mod tests {
    use super::curves::LearningCurves;
    use super::*;
    use crate::results::{Curve, CurvePoint};

    fn fixture() -> LearningCurves {
        let curve = |method: &str, slope: f64| Curve {
            method: method.into(),
            points: (0..6)
                .map(|e| CurvePoint {
                    episode: e,
                    mean: slope * f64::from(e),
                    std: 5.0,
                    seeds: 3,
                })
                .collect(),
        };
        LearningCurves {
            title: "fixture".into(),
            curves: vec![curve("cem", 10.0), curve("cem+deen", 20.0)],
        }
    }

    /// Pixels of a colour close to `c`.
    fn count(pixels: &[u8], c: RGBColor) -> usize {
        pixels
            .chunks_exact(3)
            .filter(|p| {
                (i32::from(p[0]) - i32::from(c.0)).abs() < 40
                    && (i32::from(p[1]) - i32::from(c.1)).abs() < 40
                    && (i32::from(p[2]) - i32::from(c.2)).abs() < 40
            })
            .count()
    }

    #[test]
    fn curves_render_without_a_font() {
        let pixels = render_rgb(&fixture(), false).unwrap();
        // Both methods' lines are drawn in their colours.
        assert!(
            count(&pixels, color(0)) > 300,
            "{}",
            count(&pixels, color(0))
        );
        assert!(
            count(&pixels, color(1)) > 300,
            "{}",
            count(&pixels, color(1))
        );
    }

    #[test]
    fn curves_render_with_a_font_when_there_is_one() {
        let text = fonts::ensure();
        let with = render_rgb(&fixture(), text).unwrap();
        assert!(count(&with, color(0)) > 300);
        if text {
            // Text adds dark pixels (caption, labels, legend) that the plain figure lacks.
            let without = render_rgb(&fixture(), false).unwrap();
            assert!(count(&with, BLACK) > count(&without, BLACK) + 200);
        }
    }

    #[test]
    fn padded_ranges_cover_the_values() {
        assert_eq!(padded_range([0.0, 10.0]), (-0.5, 10.5));
        assert_eq!(padded_range([3.0]), (2.5, 3.5));
        assert_eq!(padded_range([f64::NAN]), (0.0, 1.0));
    }
}
