//! The log-log plot of `furnace report`: relative MSE against render time, one curve per
//! technique, and the ideal 1/N slope through the first technique's first point. Written as
//! SVG and as PNG (drawn into an RGB buffer by plotters, encoded by `image`).

use std::path::Path;

use anyhow::{anyhow, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::report::Row;

const SIZE: (u32, u32) = (960, 640);
const FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans.ttf");

pub fn error_vs_time(rows: &[Row], svg: &Path, png: &Path) -> Result<()> {
    static FONT_ONCE: std::sync::Once = std::sync::Once::new();
    FONT_ONCE.call_once(|| {
        if plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_err() {
            tracing::warn!("the plot font did not load; text will be missing");
        }
    });
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, SIZE).into_drawing_area();
        draw(&root, rows)?;
        root.present().map_err(|e| anyhow!("plot: {e}"))?;
    }
    std::fs::write(svg, text).with_context(|| format!("cannot write {}", svg.display()))?;
    let mut buf = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, SIZE).into_drawing_area();
        draw(&root, rows)?;
        root.present().map_err(|e| anyhow!("plot: {e}"))?;
    }
    image::save_buffer_with_format(
        png,
        &buf,
        SIZE.0,
        SIZE.1,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .with_context(|| format!("cannot write {}", png.display()))?;
    Ok(())
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, rows: &[Row]) -> Result<()> {
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("plot: {e}");
    root.fill(&WHITE).map_err(err)?;
    let finite = rows.iter().filter(|r| r.seconds > 0.0 && r.rel_mse > 0.0);
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for r in finite {
        (x0, x1) = (x0.min(r.seconds), x1.max(r.seconds));
        (y0, y1) = (y0.min(r.rel_mse), y1.max(r.rel_mse));
    }
    if x0 > x1 {
        return Err(anyhow!("nothing to plot"));
    }
    let mut chart = ChartBuilder::on(root)
        .caption("error against render time", ("sans-serif", 24))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(80)
        .build_cartesian_2d((x0 / 1.5..x1 * 1.5).log_scale(), (y0 / 2.0..y1 * 2.0).log_scale())
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("render time (s)")
        .y_desc("relative MSE")
        .x_label_formatter(&|x| format!("{x:.3}"))
        .y_label_formatter(&|y| format!("{y:.0e}"))
        .draw()
        .map_err(err)?;
    for (i, name) in crate::report::technique_names(rows).iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let pts: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.technique == *name && r.rel_mse > 0.0)
            .map(|r| (r.seconds, r.rel_mse))
            .collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(err)?
            .label(*name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled()))).map_err(err)?;
    }
    // Ideal Monte Carlo convergence: relMSE proportional to 1 / time, through the first point.
    if let Some(first) = rows.first() {
        let (t0, e0) = (first.seconds, first.rel_mse);
        let ideal = [x0 / 1.5, x1 * 1.5].map(|t| (t, e0 * t0 / t));
        chart
            .draw_series(DashedLineSeries::new(ideal, 6, 4, BLACK.stroke_width(1)))
            .map_err(err)?
            .label("ideal 1/N")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(err)?;
    Ok(())
}
