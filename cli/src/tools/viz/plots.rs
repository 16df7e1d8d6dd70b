//! Precision-recall curves (VPR-Bench's, [`semlook::eval::metrics::precision_recall_curve`]) of
//! every setting of an evaluation, one chart per query set, drawn with plotters as SVG (text as
//! SVG text) and PNG (grid and curves by plotters, text in the built-in bitmap font, so no font
//! files are needed).

use super::font;
use plotters::prelude::*;
use semlook::error::{Error, Result};
use semlook::eval::metrics::precision_recall_curve;
use semlook::eval::{EvalReport, SettingReport};
use semlook::matching::Setting;
use std::path::{Path, PathBuf};

const SIZE: (u32, u32) = (720, 540);
/// The PNG's text rows above the plot area (bitmap font at scale 2, 14 px high): the title, then
/// the y axis's name below it, then the plot area (the two rows overlapped where the plot area
/// began 40 px down).
const PNG_TITLE_Y: i64 = 10;
/// The top of the y axis's name in the PNG (below the title's 14 px and a gap).
const PNG_Y_DESC_Y: i64 = 34;
/// The PNG's plot area starts this far down (below the y axis's name and room for the top tick
/// label, which is centred on its grid line).
const PNG_MARGIN_TOP: u32 = 60;
/// The PNG's rows below the plot area: the x tick labels, then the x axis's name below them (they
/// overlapped in the 40 px there were).
const PNG_X_LABEL_AREA: u32 = 52;
/// The x tick labels' top below the plot area's bottom line.
const PNG_X_TICK_GAP: i64 = 8;
/// The x axis's name's top above the picture's bottom edge.
const PNG_X_DESC_FROM_BOTTOM: i64 = 20;

// The PNG's rows of text do not overlap, checked when the crate compiles: the title, the y axis's
// name below it and the top tick label (centred on the plot area's top grid line or lower); the x
// tick labels and the x axis's name below the plot area (whose bottom line is PNG_X_LABEL_AREA
// above the picture's bottom edge). The layout of before fails them (title at 12, "precision" at
// 24, plot area from 40; ticks 6 px below it, "recall" 22 px above the edge in 40 px: "precision"
// shared the title's rows, "recall" the tick labels').
const _: () = {
    const GLYPH: i64 = 14; // 7 rows at scale 2
    assert!(PNG_TITLE_Y + GLYPH < PNG_Y_DESC_Y, "the y axis's name overlaps the title");
    assert!(PNG_Y_DESC_Y + GLYPH < PNG_MARGIN_TOP as i64 - 7, "the top tick label overlaps the y axis's name");
    let (tick_bottom, name_top) = (PNG_X_TICK_GAP + GLYPH, PNG_X_LABEL_AREA as i64 - PNG_X_DESC_FROM_BOTTOM);
    assert!(tick_bottom < name_top, "the x axis's name overlaps the tick labels");
    assert!(name_top + GLYPH <= PNG_X_LABEL_AREA as i64, "the x axis's name leaves the picture");
};
/// One colour per setting, in the order of [`Setting::ALL`] (so a setting keeps its colour in
/// every chart, whichever others ran): the baselines grey and brown, the paper's settings
/// ColorBrewer Set1, `fused` teal, and the recommended `verified` black, drawn last and
/// thickest (before, colours went by position and `verified`, ninth, wrapped to `hog`'s red).
const COLOURS: [RGBColor; 9] = [
    RGBColor(150, 150, 150),
    RGBColor(166, 86, 40),
    RGBColor(228, 26, 28),
    RGBColor(55, 126, 184),
    RGBColor(77, 175, 74),
    RGBColor(152, 78, 163),
    RGBColor(255, 127, 0),
    RGBColor(0, 150, 150),
    RGBColor(0, 0, 0),
];

/// A chart's series: label, points, colour, line width.
struct Series {
    label: String,
    points: Vec<(f64, f64)>,
    colour: RGBColor,
    width: u32,
}

/// The series of `rows` (label, points each), coloured by setting; the recommended setting
/// last and thicker, and a curve equal to one drawn before it says so in its label (it would
/// hide that one, or be hidden).
fn series_of(rows: Vec<(Setting, String, Vec<(f64, f64)>)>) -> Vec<Series> {
    let mut rows = rows;
    rows.sort_by_key(|(s, ..)| *s == Setting::RECOMMENDED);
    let mut out: Vec<Series> = Vec::with_capacity(rows.len());
    for (i, (setting, label, points)) in rows.iter().enumerate() {
        let same: Vec<&str> = rows[..i].iter().filter(|(_, _, p)| p == points).map(|(s, ..)| s.name()).collect();
        let label = if same.is_empty() { label.clone() } else { format!("{label} = {}", same.join(", ")) };
        let colour = COLOURS[Setting::ALL.iter().position(|s| s == setting).unwrap_or(0) % COLOURS.len()];
        out.push(Series { label, points: points.clone(), colour, width: if *setting == Setting::RECOMMENDED { 3 } else { 2 } });
    }
    out
}

/// (recall, precision) points of a setting's curve, queries without ground truth left out.
pub fn curve(r: &SettingReport) -> Vec<(f64, f64)> {
    let (scores, correct): (Vec<f64>, Vec<bool>) =
        r.outcomes.iter().filter(|o| o.valid_references > 0).map(|o| (o.score.map_or(f64::NEG_INFINITY, |s| s as f64), o.correct)).unzip();
    if !correct.iter().any(|&c| c) {
        return vec![(0.0, 1.0), (0.0, 0.0)];
    }
    let (p, rc) = precision_recall_curve(&scores, &correct);
    rc.into_iter().zip(p).collect()
}

fn err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::invalid(path.display().to_string(), e.to_string())
}

/// The query sets of `report`, in report order.
pub fn query_sets(report: &EvalReport) -> Vec<&str> {
    let mut sets: Vec<&str> = Vec::new();
    for r in &report.results {
        if !sets.contains(&r.query_set.as_str()) {
            sets.push(&r.query_set);
        }
    }
    sets
}

/// Every setting's precision-recall curve on query set `set`, labelled with its AUC.
fn pr_series(report: &EvalReport, set: &str) -> Vec<Series> {
    series_of(
        report
            .results
            .iter()
            .filter(|r| r.query_set == set)
            .map(|r| (r.setting, format!("{} (AUC {:.3})", r.setting.name(), r.pr.auc), curve(r)))
            .collect(),
    )
}

/// The precision-recall chart of query set `set`, as SVG text.
pub fn pr_svg(report: &EvalReport, set: &str) -> Result<String> {
    let axes = Axes { x: (0.0, 1.0), x_desc: "recall", y_desc: "precision", x_labels: 6, x_label: &|x| format!("{x:.1}"), points: false };
    svg_chart(&format!("{}: {set}", report.dataset), &pr_series(report, set), &axes)
}

/// Recall@N of every setting on query set `set` (the N of `eval.recall_at`, evenly spaced), as
/// SVG text.
pub fn recall_svg(report: &EvalReport, set: &str) -> Result<String> {
    let rows: Vec<&SettingReport> = report.results.iter().filter(|r| r.query_set == set).collect();
    let ns: Vec<usize> = rows.first().map(|r| r.recall_at.iter().map(|x| x.0).collect()).unwrap_or_default();
    let series = series_of(
        rows.iter()
            .map(|r| {
                let r1 = r.recall_at.first().map_or(0.0, |x| x.1);
                (
                    r.setting,
                    format!("{} (R@{} {r1:.3})", r.setting.name(), ns.first().unwrap_or(&1)),
                    r.recall_at.iter().enumerate().map(|(i, x)| (i as f64, x.1)).collect(),
                )
            })
            .collect(),
    );
    let label = |x: &f64| match ns.get(x.round() as usize) {
        Some(n) if (x - x.round()).abs() < 1e-6 => format!("N = {n}"),
        _ => String::new(),
    };
    let axes =
        Axes { x: (-0.2, ns.len().max(1) as f64 - 0.8), x_desc: "N", y_desc: "recall@N", x_labels: ns.len().max(1), x_label: &label, points: true };
    svg_chart(&format!("{}: {set}, recall@N", report.dataset), &series, &axes)
}

/// Writes `pr-<query set>.svg` and `.png` for every query set of `report` into `dir`.
pub fn write_pr_plots(report: &EvalReport, dir: &Path) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut written = Vec::new();
    for set in query_sets(report) {
        let slug: String = set.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '-' }).collect();
        let svg = dir.join(format!("pr-{slug}.svg"));
        std::fs::write(&svg, pr_svg(report, set)?).map_err(|e| Error::io(&svg, e))?;
        let png = dir.join(format!("pr-{slug}.png"));
        png_chart(&png, &format!("{}: {set}", report.dataset), &pr_series(report, set))?;
        written.extend([svg, png]);
    }
    Ok(written)
}

/// The x axis of a chart (y is always 0..1), and whether points get markers.
struct Axes<'a> {
    x: (f64, f64),
    x_desc: &'a str,
    y_desc: &'a str,
    x_labels: usize,
    x_label: &'a dyn Fn(&f64) -> String,
    points: bool,
}

fn svg_chart(title: &str, series: &[Series], axes: &Axes) -> Result<String> {
    let e = |e: &dyn std::fmt::Display| Error::invalid(format!("chart {title:?}"), e.to_string());
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(16)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(axes.x.0..axes.x.1, 0f64..1.02f64)
            .map_err(|x| e(&x))?;
        chart
            .configure_mesh()
            .x_desc(axes.x_desc)
            .y_desc(axes.y_desc)
            .x_labels(axes.x_labels)
            .x_label_formatter(axes.x_label)
            .draw()
            .map_err(|x| e(&x))?;
        for s in series {
            let (c, w) = (s.colour, s.width);
            chart
                .draw_series(LineSeries::new(s.points.iter().copied(), c.stroke_width(w)))
                .map_err(|x| e(&x))?
                .label(&s.label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(w)));
            if axes.points {
                chart.draw_series(s.points.iter().map(|&p| Circle::new(p, 2 + w, c.filled()))).map_err(|x| e(&x))?;
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerLeft)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|x| e(&x))?;
        root.present().map_err(|x| e(&x))?;
    }
    Ok(text)
}

fn png_chart(path: &Path, title: &str, series: &[Series]) -> Result<()> {
    let (w, h) = SIZE;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let mut ticks = Vec::new();
    let legend_at;
    {
        let root = BitMapBackend::with_buffer(&mut buf, SIZE).into_drawing_area();
        // no text through plotters (it has no font here): tick labels, title and legend are
        // drawn below in the bitmap font at the positions plotters maps them to
        let mut chart = ChartBuilder::on(&root)
            .margin_top(PNG_MARGIN_TOP)
            .margin_right(16)
            .x_label_area_size(PNG_X_LABEL_AREA)
            .y_label_area_size(50)
            .build_cartesian_2d(0f64..1.0f64, 0f64..1.02f64)
            .map_err(|e| err(path, e))?;
        chart
            .configure_mesh()
            .x_labels(0)
            .y_labels(0)
            .light_line_style(BLACK.mix(0.08))
            .bold_line_style(BLACK.mix(0.2))
            .draw()
            .map_err(|e| err(path, e))?;
        for s in series {
            chart.draw_series(LineSeries::new(s.points.iter().copied(), s.colour.stroke_width(s.width))).map_err(|e| err(path, e))?;
        }
        for k in 0..=5 {
            let v = k as f64 / 5.0;
            ticks.push((chart.backend_coord(&(v, 0.0)), format!("{v:.1}"), true));
            ticks.push((chart.backend_coord(&(0.0, v)), format!("{v:.1}"), false));
        }
        legend_at = chart.backend_coord(&(0.02, 0.02 + 0.06 * series.len() as f64));
        root.present().map_err(|e| err(path, e))?;
    }
    let mut img = image::RgbImage::from_raw(w, h, buf).ok_or_else(|| err(path, "plot buffer size"))?;
    let black = image::Rgb([0, 0, 0]);
    let text = |img: &mut image::RgbImage, x: i64, y: i64, s: &str, c: image::Rgb<u8>| {
        font::render(s, x, y, 2, |px, py| {
            if px >= 0 && py >= 0 && (px as u32) < w && (py as u32) < h {
                img.put_pixel(px as u32, py as u32, c);
            }
        })
    };
    text(&mut img, 16, PNG_TITLE_Y, title, black);
    for ((x, y), s, on_x) in &ticks {
        if *on_x {
            text(&mut img, *x as i64 - font::width(s, 2) as i64 / 2, *y as i64 + PNG_X_TICK_GAP, s, black);
        } else {
            text(&mut img, *x as i64 - font::width(s, 2) as i64 - 6, *y as i64 - 7, s, black);
        }
    }
    text(&mut img, (w / 2) as i64 - 30, h as i64 - PNG_X_DESC_FROM_BOTTOM, "recall", black);
    text(&mut img, 4, PNG_Y_DESC_Y, "precision", black);
    for (i, s) in series.iter().enumerate() {
        let (c, name) = (s.colour, &s.label);
        let (x, y) = (legend_at.0 as i64 + 4, legend_at.1 as i64 + i as i64 * 20);
        for dx in 0..20 {
            for dy in 0..3 {
                img.put_pixel((x + dx) as u32, (y + 6 + dy) as u32, image::Rgb([c.0, c.1, c.2]));
            }
        }
        text(&mut img, x + 26, y, name, black);
    }
    super::save(&img, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every setting of an evaluation of all nine gets its own colour, `verified` (the
    /// recommended one) black, drawn last and thickest, whatever the order it ran in; a curve
    /// equal to one drawn before it names it. Seen failing before: `verified`, ninth of nine,
    /// took `hog`'s red (colours by position, eight of them) and equal curves said nothing.
    #[test]
    fn each_setting_keeps_its_colour_and_equal_curves_say_so() {
        let line = |k: f64| vec![(0.0, 1.0), (1.0, k)];
        let rows: Vec<(Setting, String, Vec<(f64, f64)>)> = Setting::ALL
            .iter()
            .enumerate()
            .map(|(i, s)| (*s, s.name().to_string(), line(if *s == Setting::Fused { 0.9 } else { i as f64 / 10.0 })))
            .collect();
        let mut reversed = rows.clone();
        reversed.reverse();
        for order in [rows, reversed] {
            let mut order = order;
            // verified's curve equal to fused's
            for r in order.iter_mut().filter(|r| r.0 == Setting::Verified) {
                r.2 = line(0.9);
            }
            let series = series_of(order);
            let colours: std::collections::HashSet<(u8, u8, u8)> = series.iter().map(|s| (s.colour.0, s.colour.1, s.colour.2)).collect();
            assert_eq!(colours.len(), 9, "a colour shared");
            let last = series.last().unwrap();
            assert!(last.label.starts_with("verified") && (last.colour.0, last.colour.1, last.colour.2) == (0, 0, 0) && last.width == 3);
            assert!(last.label.ends_with("= fused"), "{}", last.label);
            assert!(series.iter().filter(|s| s.label.contains(" = ")).count() == 1);
        }
    }
}
