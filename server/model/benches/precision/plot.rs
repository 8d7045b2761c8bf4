//! Work-precision plots with plotters: error against wall time per simulated millisecond,
//! log-log, one curve per method (colour) and element family (marker), with the 1 ms haptic
//! budget and the 7 % force just-noticeable difference drawn as lines; a PNG and an SVG per
//! plot.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::anyhow;

use crate::report::{Row, Scenario};

/// DejaVu Sans 2.37, committed beside this file with its licence (`fonts/LICENSE`) and compiled
/// into the binary. plotters' `ab_glyph` backend registers a font from `&'static [u8]`;
/// `include_bytes!` gives exactly that, with no file search at run time and no leaked heap copy,
/// and the plots come out the same on every machine (the committed plots were drawn with this
/// very file, so `--replot` reproduces them byte for byte). The alternative, plotters' `ttf`
/// feature (font-kit), finds system fonts through fontconfig and FreeType: C libraries, and a
/// result that depends on the machine's fonts. The whole file (760 kB, in the bench binary only)
/// rather than an ASCII subset: a label may use any character, and an unmodified font keeps its
/// licence simple.
static DEJAVU_SANS: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");

/// Registers [`DEJAVU_SANS`] as plotters' "sans-serif", once per process.
pub fn register_font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            plotters::style::register_font(
                "sans-serif",
                plotters::style::FontStyle::Normal,
                DEJAVU_SANS,
            )
            .map_err(|_| "fonts/DejaVuSans.ttf is not a valid font".to_string())
        })
        .clone()
        .map_err(|e| anyhow!(e))
}

/// Plots of the main run: `scenario` and its error axis.
const PLOTS: [(Scenario, &str); 3] = [
    (Scenario::Lame, "relative L2 displacement error"),
    (
        Scenario::Cantilever,
        "tip deflection error vs Bisshopp-Drucker",
    ),
    (
        Scenario::LvProbe,
        "probe force error vs converged sphere reference (at its uncertainty when below it)",
    ),
];

/// The work-precision plot of every scenario with rows to draw, `dir/precision-<scenario>.png`
/// and `.svg`; returns the bases of the files written.
///
/// # Errors
/// Registering the font, or drawing or writing a plot.
pub fn scenarios(rows: &[Row], dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    register_font()?;
    std::fs::create_dir_all(dir)?;
    let mut written = Vec::new();
    for (scenario, ylabel) in PLOTS {
        let base = dir.join(format!("precision-{}", scenario.name()));
        if plot_scenario(rows, scenario, ylabel, Row::plot_error, &base)
            .map_err(|e| anyhow!("plot {}: {e}", base.display()))?
        {
            written.push(base);
        }
    }
    // The lv-probe rows' surface-displacement error (St. Venant-Kirchhoff rows).
    let base = dir.join("precision-lv-probe-surface");
    if plot_scenario(
        rows,
        Scenario::LvProbe,
        "surface displacement error at 21 epicardium points vs converged sphere solve",
        |r| r.rel_l2_error,
        &base,
    )
    .map_err(|e| anyhow!("plot {}: {e}", base.display()))?
    {
        written.push(base);
    }
    Ok(written)
}

/// The work-precision plot of the `lv-h1` rows, `dir/precision-lv-h1.png/.svg`; returns its
/// base, or `None` when there was nothing to draw.
///
/// # Errors
/// Registering the font, or drawing or writing the plot.
pub fn lv_h1(rows: &[Row], dir: &Path) -> anyhow::Result<Option<PathBuf>> {
    register_font()?;
    std::fs::create_dir_all(dir)?;
    let base = dir.join("precision-lv-h1");
    let drawn = plot_scenario(
        rows,
        Scenario::LvProbe,
        "probe force error on lv_h1.msh vs converged sphere reference (at its uncertainty when below it)",
        Row::plot_error,
        &base,
    )
    .map_err(|e| anyhow!("plot {}: {e}", base.display()))?;
    Ok(drawn.then_some(base))
}

/// The work-precision plot of `scenario`'s stable rows, `error` of each against its tick:
/// `base` with the extensions `.png` and `.svg`. Returns `false` (and draws nothing) when no
/// such row has a positive time and error.
fn plot_scenario(
    rows: &[Row],
    scenario: Scenario,
    ylabel: &str,
    error: impl Fn(&Row) -> f64,
    base: &Path,
) -> Result<bool, Box<dyn std::error::Error>> {
    let mut curves: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    let mut points = Vec::new();
    for r in rows.iter().filter(|r| r.scenario == scenario && r.stable) {
        let (x, y) = (r.step_p50_us / 1000.0, error(r));
        if x.is_finite() && x > 0.0 && y.is_finite() && y > 0.0 {
            curves.entry(r.method.clone()).or_default().push((x, y));
            let label = match r.tets {
                0 => r.method.clone(),
                n => format!("{}, {n} elements", r.method),
            };
            points.push((x, y, label));
        }
    }
    if curves.is_empty() {
        return Ok(false);
    }
    let front = pareto_front(points);
    for pts in curves.values_mut() {
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    let all = curves.values().flatten();
    let (mut x0, mut x1, mut y0, mut y1) = (1.0f64, 1.0f64, 0.07f64, 0.07f64);
    for &(x, y) in all {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    let (x0, x1, y0, y1) = (x0 / 1.5, x1 * 1.5, y0 / 1.5, y1 * 1.5);
    let title = format!("{}: error vs wall time per simulated ms", scenario.name());
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    {
        use plotters::prelude::*;
        let root = BitMapBackend::new(&png, (1250, 720)).into_drawing_area();
        draw_chart(root, &title, ylabel, &curves, &front, (x0, x1, y0, y1))?;
        let root = SVGBackend::new(&svg, (1250, 720)).into_drawing_area();
        draw_chart(root, &title, ylabel, &curves, &front, (x0, x1, y0, y1))?;
    }
    Ok(true)
}

/// The Pareto front of `(time, error, label)` points: in order of time, each point whose error
/// is more than 2 % (of itself) below that of every faster point, so that rows equal to the
/// printed digit do not crowd it.
pub fn pareto_front(mut points: Vec<(f64, f64, String)>) -> Vec<(f64, f64, String)> {
    points.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut front: Vec<(f64, f64, String)> = Vec::new();
    for p in points {
        if front.last().is_none_or(|q| p.1 < 0.98 * q.1) {
            front.push(p);
        }
    }
    front
}

/// Element family of a method label: its base method (the label without the suffix) and
/// 0 = linear tets, 1 = quadratic (" T10"), 2 = edge-smoothed linear (" ES").
fn method_family(label: &str) -> (&str, usize) {
    if let Some(b) = label.strip_suffix(" T10") {
        (b, 1)
    } else if let Some(b) = label.strip_suffix(" ES") {
        (b, 2)
    } else {
        (label, 0)
    }
}

/// Draws one work-precision chart: the plot on the left, a legend panel on the right. Colour
/// = method (integrator and setting), marker = element family, so about 30 curves stay
/// readable with a dozen legend entries; the Pareto `front` (no configuration both faster and
/// more accurate) is a black line with each of its points labelled.
fn draw_chart<DB: plotters::prelude::DrawingBackend>(
    root: plotters::drawing::DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    ylabel: &str,
    curves: &BTreeMap<String, Vec<(f64, f64)>>,
    front: &[(f64, f64, String)],
    (x0, x1, y0, y1): (f64, f64, f64, f64),
) -> Result<(), Box<dyn std::error::Error>>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    // Tableau 10, then greys.
    const COLORS: [RGBColor; 12] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
        RGBColor(188, 189, 34),
        RGBColor(23, 190, 207),
        RGBColor(60, 60, 60),
        RGBColor(170, 170, 170),
    ];
    root.fill(&WHITE)?;
    let (w, _) = root.dim_in_pixel();
    let (plot, legend) = root.split_horizontally(w.saturating_sub(350));
    let mut chart = ChartBuilder::on(&plot)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("wall time per simulated ms (ms); static: one whole solve")
        .y_desc(ylabel)
        .x_label_formatter(&|v| format!("{v:.3}"))
        .y_label_formatter(&|v| format!("{:.2}%", v * 100.0))
        .draw()?;
    let grey = RGBColor(120, 120, 120);
    let red = RGBColor(200, 60, 60);
    chart.draw_series(LineSeries::new(
        [(1.0, y0), (1.0, y1)],
        grey.stroke_width(2),
    ))?;
    chart.draw_series(LineSeries::new(
        [(x0, 0.07), (x1, 0.07)],
        red.stroke_width(2),
    ))?;
    let mut bases: Vec<&str> = curves.keys().map(|k| method_family(k).0).collect();
    bases.dedup();
    bases.sort_unstable();
    bases.dedup();
    let color_of = |base: &str| {
        let k = bases.iter().position(|b| *b == base).unwrap_or(0);
        COLORS[k % COLORS.len()]
    };
    for (name, pts) in curves {
        let (base, family) = method_family(name);
        let color = color_of(base);
        chart.draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))?;
        match family {
            0 => chart.draw_series(pts.iter().map(|&p| Cross::new(p, 5, color.stroke_width(2))))?,
            1 => chart.draw_series(pts.iter().map(|&p| Circle::new(p, 5, color.filled())))?,
            _ => chart.draw_series(
                pts.iter()
                    .map(|&p| TriangleMarker::new(p, 6, color.filled())),
            )?,
        };
    }
    // The Pareto front on top, labelled point by point.
    chart.draw_series(LineSeries::new(
        front.iter().map(|p| (p.0, p.1)),
        BLACK.stroke_width(1),
    ))?;
    let label_font = ("sans-serif", 12).into_font();
    chart.draw_series(front.iter().map(|(x, y, label)| {
        EmptyElement::at((*x, *y))
            + Circle::new((0, 0), 7, BLACK.stroke_width(1))
            + Text::new(label.clone(), (8, -16), label_font.clone())
    }))?;
    draw_legend(&legend, curves, &bases, (&color_of, [grey, red]))?;
    root.present()?;
    Ok(())
}

/// The legend panel of [`draw_chart`] (pixel coordinates): the two limits, the front, the
/// element families present, then the methods `bases` in their colours `color_of`; `grey`
/// and `red` draw the budget and JND lines.
fn draw_legend<DB: plotters::prelude::DrawingBackend>(
    legend: &plotters::drawing::DrawingArea<DB, plotters::coord::Shift>,
    curves: &BTreeMap<String, Vec<(f64, f64)>>,
    bases: &[&str],
    (color_of, [grey, red]): (
        &dyn Fn(&str) -> plotters::style::RGBColor,
        [plotters::style::RGBColor; 2],
    ),
) -> Result<(), Box<dyn std::error::Error>>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    let font = ("sans-serif", 14).into_font();
    let black = BLACK.stroke_width(2);
    let mut y = 40;
    let line = |legend: &DrawingArea<DB, plotters::coord::Shift>,
                text: &str,
                style: ShapeStyle,
                y: &mut i32|
     -> Result<(), Box<dyn std::error::Error>> {
        legend.draw(&PathElement::new([(10, *y), (40, *y)], style))?;
        legend.draw(&Text::new(text.to_string(), (48, *y - 8), font.clone()))?;
        *y += 22;
        Ok(())
    };
    line(legend, "1 ms haptic budget", grey.stroke_width(2), &mut y)?;
    line(legend, "7 % force JND", red.stroke_width(2), &mut y)?;
    line(
        legend,
        "Pareto front (labelled)",
        BLACK.stroke_width(1),
        &mut y,
    )?;
    y += 10;
    let present: Vec<usize> = curves.keys().map(|k| method_family(k).1).collect();
    for (k, text) in [
        "linear tets",
        "quadratic tets (T10)",
        "linear tets, edge smoothing (ES)",
    ]
    .iter()
    .enumerate()
    .filter(|(k, _)| present.contains(k))
    {
        let c = (25, y);
        match k {
            0 => legend.draw(&Cross::new(c, 5, black))?,
            1 => legend.draw(&Circle::new(c, 5, BLACK.filled()))?,
            _ => legend.draw(&TriangleMarker::new(c, 6, BLACK.filled()))?,
        }
        legend.draw(&Text::new(text.to_string(), (48, y - 8), font.clone()))?;
        y += 22;
    }
    y += 10;
    for base in bases {
        line(legend, base, color_of(base).stroke_width(3), &mut y)?;
    }
    Ok(())
}
