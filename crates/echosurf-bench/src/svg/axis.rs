//! A plot axis: the data range rounded to whole decades (log) or to 1, 2 or 5 times a power of ten
//! (linear), its ticks and their labels.

/// One axis: data range -> pixel range, on a linear or log10 scale.
pub(super) struct Axis {
    log: bool,
    lo: f64,
    hi: f64,
}

impl Axis {
    pub(super) fn new(values: impl Iterator<Item = f64>, log: bool) -> Axis {
        let (mut lo, mut hi) = values
            .map(|v| if log { v.log10() } else { v })
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(v), b.max(v))
            });
        if !lo.is_finite() {
            (lo, hi) = (0.0, 1.0);
        }
        if log {
            // Whole decades, so every log axis shows at least two labelled ticks.
            lo = lo.floor();
            hi = hi.ceil().max(lo + 1.0);
        } else {
            if hi - lo < 1e-12 {
                (lo, hi) = (lo - 0.5 * lo.abs().max(1.0), hi + 0.5 * hi.abs().max(1.0));
            }
            if lo > 0.0 && lo < 0.5 * hi {
                lo = 0.0;
            }
            let step = nice_step((hi - lo) / 5.0);
            lo = (lo / step).floor() * step;
            hi = (hi / step).ceil() * step;
        }
        Axis { log, lo, hi }
    }

    /// Position in [0, 1] along the axis.
    pub(super) fn fraction(&self, v: f64) -> f64 {
        let t = if self.log { v.log10() } else { v };
        (t - self.lo) / (self.hi - self.lo)
    }

    /// Tick values (data units) and their labels.
    pub(super) fn ticks(&self) -> Vec<(f64, String)> {
        if self.log {
            (self.lo as i32..=self.hi as i32)
                .map(|e| (10f64.powi(e), format_decade(e)))
                .collect()
        } else {
            let step = nice_step((self.hi - self.lo) / 5.0);
            let n = ((self.hi - self.lo) / step).round() as i64;
            (0..=n)
                .map(|i| {
                    let v = self.lo + i as f64 * step;
                    (v, format_number(v, step))
                })
                .collect()
        }
    }
}

/// 1, 2 or 5 times a power of ten, at least `raw`.
fn nice_step(raw: f64) -> f64 {
    if !(raw.is_finite() && raw > 0.0) {
        return 1.0;
    }
    let power = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * power)
        .find(|s| *s >= raw * (1.0 - 1e-9))
        .unwrap_or(10.0 * power)
}

fn format_decade(e: i32) -> String {
    match e {
        0..=5 => format!("{}", 10u64.pow(e as u32)),
        -3..=-1 => format!("{}", 10f64.powi(e)),
        _ => format!("1e{e}"),
    }
}

fn format_number(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    format!("{v:.decimals$}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_steps() {
        assert_eq!(nice_step(0.7), 1.0);
        assert_eq!(nice_step(1.3), 2.0);
        assert_eq!(nice_step(3.0), 5.0);
        assert_eq!(nice_step(20.0), 20.0);
    }
}
