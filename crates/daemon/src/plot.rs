//! What every SVG plot of the daemon shares (plotters, SVG backend: no font or bitmap
//! libraries needed): the error conversion, the legend style, padded ranges, and the moduli
//! figure that both a measurement run and `viscoprobe fit` draw.

use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// plotters' errors carry the backend's error type; the CLI only needs their text.
pub fn err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow::anyhow!("{e:?}")
}

/// A legend entry: a short line in the series' style.
pub fn legend_line<S: Into<ShapeStyle> + Copy + 'static>(
    style: S,
) -> impl Fn((i32, i32)) -> PathElement<(i32, i32)> {
    move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style)
}

/// Draws the series legend of `chart` in the house style (framed, half-transparent white).
pub fn draw_legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
) -> anyhow::Result<()> {
    chart
        .configure_series_labels()
        .border_style(BLACK)
        .background_style(WHITE.mix(0.8))
        .draw()
        .map_err(err)
}

/// (min, max) of the finite values, padded by 5 % (a flat series gets a range of its size,
/// an empty one −1…1).
pub fn padded_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (-1.0, 1.0);
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        lo.abs().max(1e-12)
    };
    (lo - pad, hi + pad)
}

/// A white SVG canvas of `size` at `path`.
pub fn canvas(path: &Path, size: (u32, u32)) -> anyhow::Result<DrawingArea<SVGBackend<'_>, Shift>> {
    let root = SVGBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    Ok(root)
}

/// The unit a modulus of about `max_pa` reads best in: (Pa per unit, name).
fn modulus_unit(max_pa: f64) -> (f64, &'static str) {
    if max_pa >= 1e6 {
        (1e6, "MPa")
    } else if max_pa >= 1e3 {
        (1e3, "kPa")
    } else {
        (1.0, "Pa")
    }
}

/// E′ and E″ (log-log, in kPa or MPa by their size) with their 95 % bands, and tan δ with its
/// band. `rows`: `[f_Hz, E′, ±E′, E″, ±E″, tan δ, ±tan δ]` (Pa), as
/// [`crate::measure::report::moduli_table`] makes them; `title` heads the left panel.
pub fn moduli(path: &Path, rows: &[[f64; 7]], title: &str) -> anyhow::Result<()> {
    let (w, h) = (900, 520);
    let positive = |v: f64| v.is_finite() && v > 0.0;
    let ok: Vec<&[f64; 7]> = rows
        .iter()
        .filter(|q| positive(q[0]) && positive(q[1]) && positive(q[3]))
        .collect();
    let (Some(first), Some(last)) = (ok.first(), ok.last()) else {
        anyhow::bail!("no frequency with a positive storage and loss modulus to plot");
    };
    let (f_lo, f_hi) = (first[0], last[0].max(first[0] * 10.0));
    let max_pa = ok.iter().map(|q| q[1].max(q[3])).fold(0.0, f64::max);
    let (unit, unit_name) = modulus_unit(max_pa);
    // The lower edge of a band is kept above 5 % of its value: a log axis has no zero.
    let lower = |v: f64, half: f64| (v - half).max(0.05 * v);
    let ymin = ok
        .iter()
        .map(|q| lower(q[1], q[2]).min(lower(q[3], q[4])))
        .fold(f64::INFINITY, f64::min)
        / unit;
    let ymax = ok
        .iter()
        .map(|q| (q[1] + q[2]).max(q[3] + q[4]))
        .fold(0.0, f64::max)
        / unit;
    let root = canvas(path, (w, h))?;
    let (left, right) = root.split_horizontally(w * 3 / 5);
    let mut c = ChartBuilder::on(&left)
        .caption(title, ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(
            (f_lo..f_hi).log_scale(),
            (ymin * 0.8..ymax * 1.2).log_scale(),
        )
        .map_err(err)?;
    c.configure_mesh()
        .x_desc("frequency, Hz")
        .y_desc(format!("modulus, {unit_name}"))
        .draw()
        .map_err(err)?;
    for (col, color, label) in [(1usize, BLUE, "E′"), (3, RED, "E″")] {
        let band: Vec<(f64, f64)> = ok
            .iter()
            .map(|q| (q[0], (q[col] + q[col + 1]) / unit))
            .chain(
                ok.iter()
                    .rev()
                    .map(|q| (q[0], lower(q[col], q[col + 1]) / unit)),
            )
            .collect();
        c.draw_series(std::iter::once(Polygon::new(band, color.mix(0.2))))
            .map_err(err)?;
        c.draw_series(LineSeries::new(
            ok.iter().map(|q| (q[0], q[col] / unit)),
            color.stroke_width(2),
        ))
        .map_err(err)?
        .label(label)
        .legend(legend_line(color.stroke_width(2)));
    }
    draw_legend(&mut c)?;
    let tmax = ok
        .iter()
        .map(|q| q[5] + q[6])
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
        * 1.1;
    let mut t = ChartBuilder::on(&right)
        .caption("loss tangent tan δ", ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d((f_lo..f_hi).log_scale(), 0.0..tmax.max(1e-3))
        .map_err(err)?;
    t.configure_mesh()
        .x_desc("frequency, Hz")
        .y_desc("tan δ")
        .draw()
        .map_err(err)?;
    let band: Vec<(f64, f64)> = ok
        .iter()
        .map(|q| (q[0], q[5] + q[6]))
        .chain(ok.iter().rev().map(|q| (q[0], (q[5] - q[6]).max(0.0))))
        .collect();
    t.draw_series(std::iter::once(Polygon::new(band, GREEN.mix(0.2))))
        .map_err(err)?;
    t.draw_series(LineSeries::new(
        ok.iter().map(|q| (q[0], q[5])),
        GREEN.stroke_width(2),
    ))
    .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn padded_range_pads_and_survives_degenerate_input() {
        assert_eq!(padded_range([1.0, 3.0].into_iter()), (0.9, 3.1));
        assert_eq!(padded_range([2.0, 2.0].into_iter()), (0.0, 4.0));
        assert_eq!(padded_range([f64::NAN].into_iter()), (-1.0, 1.0));
    }

    #[test]
    fn modulus_unit_by_size() {
        assert_eq!(modulus_unit(2.5e6).1, "MPa");
        assert_eq!(modulus_unit(1.1e3).1, "kPa");
        assert_eq!(modulus_unit(300.0).1, "Pa");
    }
}
