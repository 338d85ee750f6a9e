//! The paper's Figure 3: score estimation with DEEN against DAE on a 1-D Gaussian mixture.
//!
//! 1,000 samples of a three-component mixture are corrupted with `N(0, 0.5²)` noise during
//! training; both estimators therefore learn the *smoothed* density `p_σ = p ∗ N(0, σ²)`, whose
//! log-density and score are known in closed form (each component's variance grows by σ²). The
//! figure shows the true `p`, `log p` and score on top (with the smoothed ones dashed), and below
//! DEEN's `−E` (shifted by a constant: an energy is only defined up to one), DEEN's score `−∂E/∂x`
//! and the DAE's score estimate `(g(x) − x)/σ²`, each against the smoothed truth.

use crate::plot::{FAMILY, Figure, XAxis, chart, color, padded_range, plot_err};
use anyhow::Result;
use planner_service::energy::mixture::{self, SIGMA, density_and_score};
use planner_service::energy::{Dae, Deen, EnergyConfig};
use planner_service::nn::Normalizer;
use plotters::coord::Shift;
use plotters::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::fmt::Write as _;

/// Settings of the toy experiment.
#[derive(Clone, Debug)]
pub struct ToyConfig {
    pub samples: usize,
    pub epochs: usize,
    pub hidden_layers: usize,
    pub hidden_size: usize,
    pub seed: u64,
}

impl Default for ToyConfig {
    fn default() -> Self {
        Self {
            samples: 1000,
            epochs: 1000,
            hidden_layers: 2,
            hidden_size: 64,
            seed: 0,
        }
    }
}

/// Every curve of the figure, on one grid.
#[derive(Clone, Debug)]
pub struct ToyResult {
    pub x: Vec<f64>,
    pub density: Vec<f64>,
    pub log_density: Vec<f64>,
    pub score: Vec<f64>,
    pub smoothed_log_density: Vec<f64>,
    pub smoothed_score: Vec<f64>,
    /// `−E(x)` of the DEEN, shifted to the smoothed log-density's mean over the grid.
    pub deen_log_density: Vec<f64>,
    pub deen_score: Vec<f64>,
    pub dae_score: Vec<f64>,
}

/// Trains both estimators and evaluates everything on a grid over [−5, 5].
pub fn run(config: &ToyConfig) -> ToyResult {
    let mut rng = StdRng::seed_from_u64(config.seed);
    let data = mixture::samples(config.samples, &mut rng);
    // The estimators standardise their inputs, and σ is configured in standardised units.
    let sd = f64::from(Normalizer::fit(&data, 1).std()[0]);
    let energy = EnergyConfig {
        hidden_layers: config.hidden_layers,
        hidden_size: config.hidden_size,
        epochs: config.epochs,
        batch_size: 32,
        noise_sigma: (SIGMA / sd) as f32,
        noise_units: Default::default(),
        learning_rate: 1e-3,
    };
    let mut deen = Deen::new(1, &energy, &mut rng);
    deen.fit(&data, energy.epochs, &mut rng);
    let mut dae = Dae::new(1, &energy, &mut rng);
    dae.fit(&data, energy.epochs, &mut rng);

    let x: Vec<f64> = (0..=300)
        .map(|i| -5.0 + 10.0 * f64::from(i) / 300.0)
        .collect();
    let grid: Vec<f32> = x.iter().map(|&v| v as f32).collect();
    let truth: Vec<(f64, f64)> = x.iter().map(|&y| density_and_score(y, 0.0)).collect();
    let smoothed: Vec<(f64, f64)> = x
        .iter()
        .map(|&y| density_and_score(y, SIGMA * SIGMA))
        .collect();
    let smoothed_log_density: Vec<f64> = smoothed.iter().map(|s| s.0.ln()).collect();
    let neg_energy: Vec<f64> = deen
        .energy_rows(&grid)
        .iter()
        .map(|&e| -f64::from(e))
        .collect();
    let shift = mean(&smoothed_log_density) - mean(&neg_energy);
    // g(x) − x ≈ σ_std² ∇ log p_σ in standardised units; ∇ in raw units divides by sd once more.
    let sigma_std = f64::from(energy.noise_sigma);
    ToyResult {
        density: truth.iter().map(|t| t.0).collect(),
        log_density: truth.iter().map(|t| t.0.ln()).collect(),
        score: truth.iter().map(|t| t.1).collect(),
        smoothed_score: smoothed.iter().map(|s| s.1).collect(),
        smoothed_log_density,
        deen_log_density: neg_energy.iter().map(|v| v + shift).collect(),
        deen_score: deen
            .score_rows(&grid)
            .iter()
            .map(|&v| f64::from(v))
            .collect(),
        dae_score: dae
            .displacement_rows(&grid)
            .iter()
            .map(|&v| f64::from(v) / (sigma_std * sigma_std * sd))
            .collect(),
        x,
    }
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

impl ToyResult {
    /// The curves as CSV, one row per grid point.
    pub fn to_csv(&self) -> String {
        let mut out = String::from(
            "x,density,log_density,score,smoothed_log_density,smoothed_score,deen_log_density,deen_score,dae_score\n",
        );
        for i in 0..self.x.len() {
            let _ = writeln!(
                out,
                "{:.4},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6}",
                self.x[i],
                self.density[i],
                self.log_density[i],
                self.score[i],
                self.smoothed_log_density[i],
                self.smoothed_score[i],
                self.deen_log_density[i],
                self.deen_score[i],
                self.dae_score[i]
            );
        }
        out
    }

    /// Root-mean-square error of each estimator's score against the smoothed score, over the
    /// part of the grid where the data lives (|x| ≤ 4).
    pub fn score_rmse(&self) -> (f64, f64) {
        let rmse = |est: &[f64]| {
            let errors: Vec<f64> = self
                .x
                .iter()
                .zip(est.iter().zip(&self.smoothed_score))
                .filter(|(x, _)| x.abs() <= 4.0)
                .map(|(_, (e, t))| (e - t).powi(2))
                .collect();
            (errors.iter().sum::<f64>() / errors.len().max(1) as f64).sqrt()
        };
        (rmse(&self.deen_score), rmse(&self.dae_score))
    }
}

/// One panel: curves `(values, label, dashed)` over the grid.
type Panel<'a> = (&'a str, &'a str, Vec<(&'a [f64], &'a str, bool)>);

impl Figure for ToyResult {
    fn size(&self) -> (u32, u32) {
        (1200, 680)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, text: bool) -> Result<()> {
        let panels: [Panel; 6] = [
            ("p(x)", "p", vec![(&self.density, "p(x)", false)]),
            (
                "log p(x)",
                "log p",
                vec![
                    (&self.log_density, "log p(x)", false),
                    (&self.smoothed_log_density, "log p_σ(x)", true),
                ],
            ),
            (
                "score ∂log p/∂x",
                "score",
                vec![
                    (&self.score, "of p", false),
                    (&self.smoothed_score, "of p_σ", true),
                ],
            ),
            (
                "DEEN: −E(x) + c",
                "log p",
                vec![
                    (&self.deen_log_density, "DEEN −E + c", false),
                    (&self.smoothed_log_density, "log p_σ", true),
                ],
            ),
            (
                "DEEN: score −∂E/∂x",
                "score",
                vec![
                    (&self.deen_score, "DEEN", false),
                    (&self.smoothed_score, "true (p_σ)", true),
                ],
            ),
            (
                "DAE: score (g(x) − x)/σ²",
                "score",
                vec![
                    (&self.dae_score, "DAE", false),
                    (&self.smoothed_score, "true (p_σ)", true),
                ],
            ),
        ];
        let areas = root.split_evenly((2, 3));
        let xr = (self.x[0], self.x[self.x.len() - 1]);
        for (area, (title, unit, curves)) in areas.iter().zip(panels) {
            // log p falls off a cliff in the tails; clip the axis where the data is.
            let yr = padded_range(
                curves
                    .iter()
                    .flat_map(|(v, _, _)| v.iter().copied().map(|y| y.max(-12.0))),
            );
            let mut c = chart(area, title, (xr, XAxis::Continuous), yr, ("x", unit), text)?;
            for (i, (values, label, dashed)) in curves.iter().enumerate() {
                let colour = if *dashed {
                    BLACK.mix(0.6)
                } else {
                    color(i).mix(1.0)
                };
                let points: Vec<(f64, f64)> = self
                    .x
                    .iter()
                    .zip(values.iter())
                    .map(|(&x, &y)| (x, y.max(yr.0)))
                    .collect();
                let style = colour.stroke_width(2);
                let series = if *dashed {
                    c.draw_series(DashedLineSeries::new(points, 6, 4, style))
                        .map_err(plot_err)?
                } else {
                    c.draw_series(LineSeries::new(points, style))
                        .map_err(plot_err)?
                };
                if text {
                    series
                        .label(*label)
                        .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], style));
                }
            }
            if text && curves.len() > 1 {
                c.configure_series_labels()
                    .position(SeriesLabelPosition::UpperRight)
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK.mix(0.3))
                    .label_font((FAMILY, 12))
                    .draw()
                    .map_err(plot_err)?;
            }
        }
        Ok(())
    }
}
