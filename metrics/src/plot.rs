//! Line charts as SVG: the training loss with its running mean (`bwm train`'s `loss.svg`), and
//! labelled curves on one chart (the fidelity report's PSNR and SSIM by frame).

use std::path::Path;

use anyhow::{ensure, Result};
use plotters::prelude::*;

/// Draws the per-step loss and its running mean (window 10% of the run) to an SVG file.
pub fn loss_plot(losses: &[(u64, f64)], title: &str, out: &Path) -> Result<()> {
    ensure!(!losses.is_empty(), "no logged loss to plot");
    let finite: Vec<(u64, f64)> = losses.iter().copied().filter(|(_, l)| l.is_finite()).collect();
    ensure!(!finite.is_empty(), "no finite loss to plot");
    let window = (finite.len() / 10).max(1);
    let smooth: Vec<(u64, f64)> = (0..finite.len())
        .map(|i| {
            let lo = i.saturating_sub(window - 1);
            let s = &finite[lo..=i];
            (finite[i].0, s.iter().map(|(_, l)| l).sum::<f64>() / s.len() as f64)
        })
        .collect();
    let max_step = finite.last().map(|(s, _)| *s).unwrap_or(1).max(1);
    let max_loss = finite.iter().map(|(_, l)| *l).fold(0.0, f64::max) * 1.05;
    let root = SVGBackend::new(out, (900, 500)).into_drawing_area();
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0u64..max_step, 0f64..max_loss)?;
        chart.configure_mesh().x_desc("optimizer step").y_desc("weighted flow-matching loss").draw()?;
        chart
            .draw_series(LineSeries::new(finite.iter().copied(), RGBColor(170, 190, 230)))?
            .label("per step")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RGBColor(170, 190, 230)));
        chart
            .draw_series(LineSeries::new(smooth.iter().copied(), BLUE.stroke_width(2)))?
            .label(format!("mean of last {window}"))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| anyhow::anyhow!("drawing {}: {e}", out.display()))
}

/// Lines `(label, points)` on one chart, written as SVG (fidelity curves and the like).
pub fn line_plot(series: &[(String, Vec<(f64, f64)>)], title: &str, x_desc: &str, y_desc: &str, out: &Path) -> Result<()> {
    let points = || series.iter().flat_map(|(_, p)| p.iter().copied()).filter(|(x, y)| x.is_finite() && y.is_finite());
    ensure!(points().next().is_some(), "no finite points to plot");
    let (x_lo, x_hi) = points().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (x, _)| (lo.min(x), hi.max(x)));
    let (y_lo, y_hi) = points().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (_, y)| (lo.min(y), hi.max(y)));
    let pad = ((y_hi - y_lo) * 0.05).max(1e-3);
    let palette = [BLUE, RED, RGBColor(0, 150, 0), MAGENTA, RGBColor(230, 140, 0), CYAN, BLACK];
    let root = SVGBackend::new(out, (900, 500)).into_drawing_area();
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x_lo..x_hi.max(x_lo + 1.0), (y_lo - pad)..(y_hi + pad))?;
        chart.configure_mesh().x_desc(x_desc).y_desc(y_desc).draw()?;
        for (i, (label, pts)) in series.iter().enumerate() {
            let color = palette[i % palette.len()];
            chart
                .draw_series(LineSeries::new(pts.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite()), color.stroke_width(2)))?
                .label(label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| anyhow::anyhow!("drawing {}: {e}", out.display()))
}
