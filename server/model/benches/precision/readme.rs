//! The README-sized work-precision plot of the LV press, `precision-lv-probe-readme.png` /
//! `.svg`: at most 8 labelled series, the configurations the shipped LV scenes run
//! ([`SHIPPED`]), the Pareto front over every `lv-probe` and `lv-h1` row, and the other rows as
//! one grey series; probe-force error against the sphere reference of each row's own material
//! against wall time per simulated ms, as the full plot `precision-lv-probe.png`.
//!
//! How rows are matched to shipped scenes: by the exact method label of the bench row that
//! builds the scene's configuration ([`SHIPPED`]). Those rows are built from the scene itself
//! (`load_builtin` or the scene file, with nothing changed but, for `lv`, the probe contact
//! model written out as the one `auto` resolves to on an FEM body), so their material, mesh,
//! integrator and contact are the scene's: `lv` = "lv default, contact patch-local T10"
//! ([`crate::lv_probe::contact_rows`]), `lv-hybrid` = "hybrid corrected"
//! ([`crate::lv_probe::hybrid_rows`]), `lv-surface-springs` = "lv-surface-springs (scene)"
//! ([`crate::lv_probe::mass_spring_rows`]), and the `lv_h1` scenes = their "(scene)" rows of
//! the `lv-h1` scenario ([`crate::lv_h1::scene_rows`]) when those results exist.

use std::path::{Path, PathBuf};

use anyhow::anyhow;

use crate::plot::{pareto_front, register_font};
use crate::report::{Row, Scenario};

/// The shipped LV scenes and the method label of the bench row that runs each one's
/// configuration (see the module documentation). At most 6, so that with the Pareto front
/// and the other rows the plot has at most 8 labelled series.
pub const SHIPPED: &[(&str, &str)] = &[
    ("lv", "lv default, contact patch-local T10"),
    ("lv-hybrid", "hybrid corrected"),
    ("lv-surface-springs", "lv-surface-springs (scene)"),
    ("lv_h1", "lv_h1 (scene) ES"),
    ("lv_h1_es", "lv_h1_es (scene) ES"),
    ("lv_h1_condensed", "lv_h1_condensed (scene) ES"),
];

/// One drawn point: wall time per simulated ms (ms), error, label.
type Point = (f64, f64, String);

/// The README plot of `rows` (the `lv-probe` rows are used, of both result files) as
/// `dir/precision-lv-probe-readme.png` and `.svg`; returns its base, or `None` when no row can
/// be drawn.
///
/// # Errors
/// Registering the font, or drawing or writing the plot.
pub fn readme(rows: &[Row], dir: &Path) -> anyhow::Result<Option<PathBuf>> {
    register_font()?;
    std::fs::create_dir_all(dir)?;
    let mut shipped: Vec<(String, Point)> = Vec::new();
    let mut all: Vec<Point> = Vec::new();
    for r in rows
        .iter()
        .filter(|r| r.scenario == Scenario::LvProbe && r.stable)
    {
        let (x, y) = (r.step_p50_us / 1000.0, r.plot_error());
        if !(x.is_finite() && x > 0.0 && y.is_finite() && y > 0.0) {
            continue;
        }
        // The material once (FEM method labels carry it already unless StVK), shortened.
        let method = r.method.replace("stable-neo-hookean", "neo-Hookean");
        let material = if r.method.contains('[') {
            String::new()
        } else {
            format!(
                " [{}]",
                r.material.replace("stable-neo-hookean", "neo-Hookean")
            )
        };
        let label = match r.tets {
            0 => format!("{method}{material}"),
            n => format!("{method}{material}, {n} el."),
        };
        if let Some((scene, _)) = SHIPPED.iter().find(|(_, m)| *m == r.method) {
            shipped.push((format!("{scene}: {label}"), (x, y, label.clone())));
        }
        all.push((x, y, label));
    }
    if all.is_empty() {
        return Ok(None);
    }
    let front = pareto_front(all.clone());
    let base = dir.join("precision-lv-probe-readme");
    let (mut x0, mut x1, mut y0, mut y1) = (1.0f64, 1.0f64, 0.07f64, 0.07f64);
    for (x, y, _) in &all {
        (x0, x1, y0, y1) = (x0.min(*x), x1.max(*x), y0.min(*y), y1.max(*y));
    }
    let bounds = (x0 / 1.5, x1 * 1.5, y0 / 1.5, y1 * 1.5);
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    {
        use plotters::prelude::*;
        let root = BitMapBackend::new(&png, (1200, 560)).into_drawing_area();
        draw(root, &all, &front, &shipped, bounds)
            .map_err(|e| anyhow!("plot {}: {e}", png.display()))?;
        let root = SVGBackend::new(&svg, (1200, 560)).into_drawing_area();
        draw(root, &all, &front, &shipped, bounds)
            .map_err(|e| anyhow!("plot {}: {e}", svg.display()))?;
    }
    Ok(Some(base))
}

/// Draws the README chart: every row as a small grey dot, the Pareto `front` as a black line
/// through numbered points (the numbers listed in the legend), and each shipped scene's row
/// as a large coloured marker with its own legend entry.
fn draw<DB: plotters::prelude::DrawingBackend>(
    root: plotters::drawing::DrawingArea<DB, plotters::coord::Shift>,
    all: &[Point],
    front: &[Point],
    shipped: &[(String, Point)],
    (x0, x1, y0, y1): (f64, f64, f64, f64),
) -> Result<(), Box<dyn std::error::Error>>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    const COLORS: [RGBColor; 6] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(227, 119, 194),
    ];
    root.fill(&WHITE)?;
    let (w, _) = root.dim_in_pixel();
    let (plot, legend) = root.split_horizontally(w.saturating_sub(500));
    let mut chart = ChartBuilder::on(&plot)
        .caption(
            "LV probe press: force error vs wall time per simulated ms",
            ("sans-serif", 18),
        )
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("wall time per simulated ms (ms, median tick)")
        .y_desc("largest probe-force error vs sphere reference")
        .x_label_formatter(&|v| format!("{v:.3}"))
        .y_label_formatter(&|v| format!("{:.1}%", v * 100.0))
        .draw()?;
    let grey = RGBColor(120, 120, 120);
    let light = RGBColor(185, 185, 185);
    let red = RGBColor(200, 60, 60);
    chart.draw_series(LineSeries::new(
        [(1.0, y0), (1.0, y1)],
        grey.stroke_width(2),
    ))?;
    chart.draw_series(LineSeries::new(
        [(x0, 0.07), (x1, 0.07)],
        red.stroke_width(2),
    ))?;
    chart.draw_series(
        all.iter()
            .map(|p| Circle::new((p.0, p.1), 3, light.filled())),
    )?;
    chart.draw_series(LineSeries::new(
        front.iter().map(|p| (p.0, p.1)),
        BLACK.stroke_width(1),
    ))?;
    let number_font = ("sans-serif", 13).into_font();
    chart.draw_series(front.iter().enumerate().map(|(k, p)| {
        EmptyElement::at((p.0, p.1))
            + Circle::new((0, 0), 5, BLACK.stroke_width(1))
            + Text::new(format!("{}", k + 1), (5, -17), number_font.clone())
    }))?;
    for (k, (_, p)) in shipped.iter().enumerate() {
        let c = COLORS[k % COLORS.len()];
        chart.draw_series(std::iter::once(
            EmptyElement::at((p.0, p.1))
                + Circle::new((0, 0), 8, c.filled())
                + Circle::new((0, 0), 8, BLACK.stroke_width(1)),
        ))?;
    }
    draw_legend(&legend, front, shipped, (&COLORS, [grey, light, red]))?;
    root.present()?;
    Ok(())
}

/// The legend panel of [`draw`] (pixel coordinates): the lines, the shipped scenes, the
/// front's points; `colors` of the shipped scenes, then the budget, other-row and JND colours.
fn draw_legend<DB: plotters::prelude::DrawingBackend>(
    legend: &plotters::drawing::DrawingArea<DB, plotters::coord::Shift>,
    front: &[Point],
    shipped: &[(String, Point)],
    (colors, [grey, light, red]): (&[plotters::style::RGBColor], [plotters::style::RGBColor; 3]),
) -> Result<(), Box<dyn std::error::Error>>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    let font = ("sans-serif", 13).into_font();
    let small = ("sans-serif", 11).into_font();
    let mut y = 30;
    for (text, style) in [
        ("1 ms haptic budget", grey.stroke_width(2)),
        ("7 % force JND", red.stroke_width(2)),
    ] {
        legend.draw(&PathElement::new([(8, y), (34, y)], style))?;
        legend.draw(&Text::new(text, (42, y - 7), font.clone()))?;
        y += 20;
    }
    legend.draw(&Circle::new((21, y), 3, light.filled()))?;
    legend.draw(&Text::new(
        "every other configuration run",
        (42, y - 7),
        font.clone(),
    ))?;
    y += 28;
    legend.draw(&Text::new("shipped scenes:", (8, y - 7), font.clone()))?;
    y += 20;
    for (k, (text, _)) in shipped.iter().enumerate() {
        let c = colors[k % colors.len()];
        legend.draw(&Circle::new((21, y), 7, c.filled()))?;
        legend.draw(&Text::new(text.clone(), (42, y - 7), small.clone()))?;
        y += 20;
    }
    y += 8;
    legend.draw(&PathElement::new([(8, y), (34, y)], BLACK.stroke_width(1)))?;
    legend.draw(&Text::new(
        "Pareto front (none faster and more accurate):",
        (42, y - 7),
        font.clone(),
    ))?;
    y += 20;
    for (k, p) in front.iter().enumerate() {
        legend.draw(&Text::new(
            format!("{}  {}", k + 1, p.2),
            (20, y - 7),
            small.clone(),
        ))?;
        y += 16;
    }
    Ok(())
}
