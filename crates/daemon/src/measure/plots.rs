//! SVG plots of a run (plotters, SVG backend: no font or bitmap libraries needed).

use super::report::{moduli_table, RunReport, REPORT_BAND_HZ};
use crate::plot::{canvas, draw_legend, err, legend_line};
use anyhow::Context;
use plotters::prelude::*;
use std::path::Path;
use viscoprobe_core::prony::PronySeries;

const W: u32 = 900;
const H: u32 = 520;

/// Writes every plot the report has data for.
pub fn write_all(dir: &Path, report: &RunReport) -> anyhow::Result<()> {
    if report.iterations.is_empty() {
        return Ok(());
    }
    convergence(&dir.join("convergence.svg"), report).context("convergence.svg")?;
    moduli(&dir.join("moduli.svg"), report).context("moduli.svg")?;
    tracking(&dir.join("tracking.svg"), report).context("tracking.svg")?;
    design(&dir.join("design.svg"), report).context("design.svg")?;
    Ok(())
}

/// Each parameter relative to the truth (simulations) or the final estimate, %, with 95 % bars.
fn convergence(path: &Path, r: &RunReport) -> anyhow::Result<()> {
    let last = r.last().expect("checked");
    let n = last.params.len();
    let names = PronySeries::param_names((n - 1) / 2);
    let reference: Vec<f64> = match &r.truth {
        Some(t) if t.n_params() == n => t.to_vec(),
        _ => last.params.clone(),
    };
    let rel = |v: f64, i: usize| 100.0 * (v - reference[i]) / reference[i];
    let mut lo = -1.0f64;
    let mut hi = 1.0f64;
    for it in &r.iterations {
        for i in 0..n {
            lo = lo.min(rel(it.ci95[i][0], i)).max(-100.0);
            hi = hi.max(rel(it.ci95[i][1], i)).min(100.0);
        }
    }
    let root = canvas(path, (W, H))?;
    let what = if r.truth.is_some() {
        "truth"
    } else {
        "final estimate"
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("Parameter convergence (relative to the {what}, 95 % intervals)"),
            ("sans-serif", 18),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.5f64..(r.iterations.len() as f64 + 0.5), lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("design iteration")
        .y_desc("deviation, %")
        .draw()
        .map_err(err)?;
    #[allow(clippy::needless_range_loop)] // i indexes params, names and intervals alike
    for i in 0..n {
        let color = Palette99::pick(i).to_rgba();
        let off = (i as f64 - n as f64 / 2.0) * 0.03;
        let pts: Vec<(f64, f64)> = r
            .iterations
            .iter()
            .map(|it| {
                (
                    it.iteration as f64 + off,
                    rel(it.params[i], i).clamp(lo, hi),
                )
            })
            .collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(err)?
            .label(names[i].clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
        chart
            .draw_series(r.iterations.iter().map(|it| {
                let x = it.iteration as f64 + off;
                PathElement::new(
                    vec![
                        (x, rel(it.ci95[i][0], i).clamp(lo, hi)),
                        (x, rel(it.ci95[i][1], i).clamp(lo, hi)),
                    ],
                    color.stroke_width(1),
                )
            }))
            .map_err(err)?;
    }
    draw_legend(&mut chart)?;
    root.present().map_err(err)?;
    Ok(())
}

/// E′ and E″ with 95 % bands, and tan δ.
fn moduli(path: &Path, r: &RunReport) -> anyhow::Result<()> {
    let Some(est) = r.last().and_then(|l| l.estimate.as_ref()) else {
        return Ok(());
    };
    crate::plot::moduli(
        path,
        &moduli_table(est, REPORT_BAND_HZ),
        "Storage E′ and loss E″ modulus (95 % bands)",
    )
}

/// Desired versus achieved force over one period of the final iteration.
fn tracking(path: &Path, r: &RunReport) -> anyhow::Result<()> {
    let last = r.last().expect("checked");
    let (idx, desired, achieved) = &last.force_period;
    if idx.is_empty() {
        return Ok(());
    }
    let fs = r.sample_rate_hz;
    let lo = desired
        .iter()
        .chain(achieved)
        .copied()
        .fold(f64::INFINITY, f64::min);
    let hi = desired
        .iter()
        .chain(achieved)
        .copied()
        .fold(f64::NEG_INFINITY, f64::max);
    let root = canvas(path, (W, H))?;
    let t_end = idx.last().copied().unwrap_or(1.0) / fs;
    let mut c = ChartBuilder::on(&root)
        .caption(
            format!(
                "Desired vs achieved deflection (force), one period — err₂ {:.2} %, err∞ {:.2} %",
                last.tracking.err2_pct, last.tracking.errinf_pct
            ),
            ("sans-serif", 16),
        )
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, lo..hi)
        .map_err(err)?;
    c.configure_mesh()
        .x_desc("time, s")
        .y_desc("deflection, V")
        .draw()
        .map_err(err)?;
    c.draw_series(LineSeries::new(
        idx.iter().zip(desired).map(|(i, v)| (i / fs, *v)),
        BLACK.stroke_width(2),
    ))
    .map_err(err)?
    .label("desired")
    .legend(legend_line(BLACK.stroke_width(2)));
    c.draw_series(LineSeries::new(
        idx.iter().zip(achieved).map(|(i, v)| (i / fs, *v)),
        RED.stroke_width(1),
    ))
    .map_err(err)?
    .label("achieved (mean of the periods)")
    .legend(legend_line(RED.stroke_width(1)));
    draw_legend(&mut c)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Power per line of every iteration's design (stems, log frequency).
fn design(path: &Path, r: &RunReport) -> anyhow::Result<()> {
    let fmax = r
        .iterations
        .iter()
        .flat_map(|it| it.lines.iter().map(|l| l.freq_hz))
        .fold(1.0, f64::max);
    let root = canvas(path, (W, H))?;
    let mut c = ChartBuilder::on(&root)
        .caption(
            "Excitation design per iteration: power fraction per line",
            ("sans-serif", 16),
        )
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((0.5f64..fmax * 2.0).log_scale(), 0.0..1.0f64)
        .map_err(err)?;
    c.configure_mesh()
        .x_desc("frequency, Hz")
        .y_desc("power fraction")
        .draw()
        .map_err(err)?;
    let n = r.iterations.len();
    for (k, it) in r.iterations.iter().enumerate() {
        let color = if k + 1 == n {
            RED.to_rgba()
        } else {
            BLUE.mix(0.15 + 0.5 * k as f64 / n as f64)
        };
        let shift = 1.0 + 0.01 * k as f64;
        c.draw_series(it.lines.iter().map(|l| {
            PathElement::new(
                vec![(l.freq_hz * shift, 0.0), (l.freq_hz * shift, l.power_frac)],
                color.stroke_width(3),
            )
        }))
        .map_err(err)?;
    }
    root.present().map_err(err)?;
    Ok(())
}
