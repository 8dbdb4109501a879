//! Image filters the band logic needs, all on row-major `f32` crops: separable Gaussian smoothing,
//! column edgels (non-maximum-suppressed vertical gradients) and a truncated exact Euclidean distance
//! transform. Every buffer is owned by the caller and reused from frame to frame; rows are processed in
//! parallel and results are gathered in row order, so output never depends on the thread count.

use rayon::prelude::*;

/// Normalised 1D Gaussian taps for `sigma_px`, radius `ceil(3 sigma)`; a single unit tap for sigma <= 0.
pub fn gaussian_taps(sigma_px: f64) -> Vec<f32> {
    if sigma_px.is_nan() || sigma_px <= 0.0 {
        return vec![1.0];
    }
    let radius = (3.0 * sigma_px).ceil() as i64;
    let taps: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma_px * sigma_px)).exp())
        .collect();
    let sum: f64 = taps.iter().sum();
    taps.iter().map(|t| (t / sum) as f32).collect()
}

/// Separable Gaussian smoothing with replicated borders: `src` (w x h) -> `out`, `tmp` is scratch.
pub fn smooth(
    src: &[f32],
    width: usize,
    height: usize,
    taps: &[f32],
    tmp: &mut Vec<f32>,
    out: &mut Vec<f32>,
) {
    let n = width * height;
    tmp.resize(n, 0.0);
    out.resize(n, 0.0);
    if n == 0 {
        return;
    }
    let radius = (taps.len() / 2) as isize;
    // Horizontal pass, one row per task.
    tmp.par_chunks_mut(width)
        .zip(src.par_chunks(width))
        .for_each(|(dst, row)| {
            let last = width as isize - 1;
            for (u, d) in dst.iter_mut().enumerate() {
                let u = u as isize;
                let mut acc = 0.0f32;
                if u - radius >= 0 && u + radius <= last {
                    let start = (u - radius) as usize;
                    for (t, x) in taps.iter().zip(&row[start..start + taps.len()]) {
                        acc += t * x;
                    }
                } else {
                    for (k, t) in taps.iter().enumerate() {
                        let j = (u + k as isize - radius).clamp(0, last) as usize;
                        acc += t * row[j];
                    }
                }
                *d = acc;
            }
        });
    // Vertical pass: each output row is a weighted sum of whole input rows (vectorises along the row).
    let tmp_ref: &[f32] = tmp;
    out.par_chunks_mut(width).enumerate().for_each(|(v, dst)| {
        dst.fill(0.0);
        let last = height as isize - 1;
        for (k, t) in taps.iter().enumerate() {
            let j = (v as isize + k as isize - radius).clamp(0, last) as usize;
            let row = &tmp_ref[j * width..(j + 1) * width];
            for (d, x) in dst.iter_mut().zip(row) {
                *d += t * x;
            }
        }
    });
}

/// Which sign of the vertical derivative (down the column, i.e. with depth) makes an edgel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum EdgePolarity {
    /// dI/dv > 0: dark above, bright below, i.e. entering an echo from the probe side.
    Rising,
    /// dI/dv < 0: leaving an echo (into its shadow).
    Falling,
    /// |dI/dv|.
    Both,
}

/// How edgels are chosen (see [`strongest_column_edgels`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EdgelSelection {
    /// M.
    pub count: usize,
    pub min_strength: f32,
    pub relative_floor: f32,
    pub reference_at_least: f32,
    pub polarity: EdgePolarity,
    /// Keep only the strongest edgel of each column (a boundary crosses a column once; see
    /// `SegmentOptions::edgel_chaining`).
    pub per_column: bool,
    /// With `per_column`: an edgel weaker than the floor is still kept if it is at least `weak_fraction`
    /// of the floor and chained to an edgel above the floor through edgels of consecutive columns whose
    /// rows differ by at most `link_rows` (hysteresis). 1 (or `link_rows` 0) = no chaining.
    pub weak_fraction: f32,
    pub link_rows: usize,
    /// With `per_column`: chains spanning fewer columns are dropped (speckle grains are short).
    pub min_chain_columns: usize,
    /// With `per_column`: how many boundaries one column may cross (a wall seen through another, as a
    /// hollow organ's far wall through its near one). Each layer after the first takes, per column, the
    /// strongest candidate more than `layer_gap_rows` from the edgels already kept there (where none is
    /// kept: the strongest not offered to an earlier layer) and chains those under the same floor.
    /// 1 = one boundary per column.
    pub layers: usize,
    pub layer_gap_rows: usize,
}

/// One edgel: a local maximum along its column of the vertical gradient magnitude.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Edgel {
    /// |dI/dv| of the smoothed image, grey levels per pixel.
    pub strength: f32,
    /// Row-major index `v * width + u` in the crop.
    pub index: u32,
}

/// Strongest first; between equals the lower index (the upper row), so every choice is deterministic.
fn strongest_first(a: &Edgel, b: &Edgel) -> std::cmp::Ordering {
    b.strength
        .total_cmp(&a.strength)
        .then(a.index.cmp(&b.index))
}

/// The `count` strongest column edgels of a smoothed image: pixels whose central-difference vertical
/// gradient (of the chosen polarity) exceeds `min_strength` and `relative_floor` times the strength of
/// the edgel ranked at the top 5 % (or of `reference_at_least` if larger), and is a maximum along the column (echoes travel down the
/// columns, so a boundary crosses each column once; suppressing non-maxima turns one blurred edge into one
/// edgel per column instead of several). Ties are broken by index, so the choice is deterministic.
/// Returns this frame's reference strength (the edgel ranked at the top 5 %).
pub fn strongest_column_edgels(
    smoothed: &[f32],
    width: usize,
    height: usize,
    selection: &EdgelSelection,
    out: &mut Vec<Edgel>,
) -> f32 {
    let EdgelSelection {
        count,
        min_strength,
        relative_floor,
        reference_at_least,
        polarity,
        per_column,
        ..
    } = *selection;
    out.clear();
    if height < 5 || width == 0 || count == 0 {
        return 0.0;
    }
    let grad = |u: usize, v: usize| -> f32 {
        let g = 0.5 * (smoothed[(v + 1) * width + u] - smoothed[(v - 1) * width + u]);
        match polarity {
            EdgePolarity::Rising => g,
            EdgePolarity::Falling => -g,
            EdgePolarity::Both => g.abs(),
        }
    };
    let rows: Vec<Vec<Edgel>> = (2..height - 2)
        .into_par_iter()
        .map(|v| {
            let mut found = Vec::new();
            for u in 0..width {
                let g = grad(u, v);
                if g > min_strength && g > grad(u, v - 1) && g >= grad(u, v + 1) {
                    found.push(Edgel {
                        strength: g,
                        index: (v * width + u) as u32,
                    });
                }
            }
            found
        })
        .collect();
    if per_column {
        // Every candidate of each column, top to bottom, and the strongest one (ties: the upper one).
        let mut columns: Vec<Vec<Edgel>> = vec![Vec::new(); width];
        let mut best: Vec<Option<Edgel>> = vec![None; width];
        for r in rows {
            for e in r {
                let u = e.index as usize % width;
                if best[u].is_none_or(|b| e.strength > b.strength) {
                    best[u] = Some(e);
                }
                columns[u].push(e);
            }
        }
        return chained_column_edgels(&best, &columns, width, selection, out);
    }
    for r in rows {
        out.extend(r);
    }
    if out.len() > count {
        out.select_nth_unstable_by(count - 1, strongest_first);
        out.truncate(count);
    }
    let mut reference = 0.0f32;
    if !out.is_empty() {
        // Robust maximum: the strength ranked at the top 5 % of the kept edgels.
        out.sort_unstable_by(strongest_first);
        reference = out[out.len() / 20].strength;
        if relative_floor > 0.0 {
            let floor = relative_floor * reference.max(reference_at_least);
            out.retain(|e| e.strength >= floor);
        }
    }
    out.sort_unstable_by_key(|e| e.index);
    reference
}

/// Selection on one candidate per column (`best[u]`): the M strongest, then the relative floor with
/// hysteresis along chains of neighbouring columns; then, for each further layer, the same on the next
/// candidate of each column (see [`EdgelSelection::layers`]). Returns the reference strength (top 5 %
/// of the first layer).
fn chained_column_edgels(
    best: &[Option<Edgel>],
    columns: &[Vec<Edgel>],
    width: usize,
    selection: &EdgelSelection,
    out: &mut Vec<Edgel>,
) -> f32 {
    let mut ranked = strongest_m(best, selection.count);
    if ranked.is_empty() {
        return 0.0;
    }
    let reference = ranked[ranked.len() / 20].strength;
    let floor = selection.relative_floor * reference.max(selection.reference_at_least);
    let weak_floor = if selection.link_rows == 0 {
        floor
    } else {
        floor * selection.weak_fraction.min(1.0)
    };
    let row = |e: &Edgel| (e.index as usize / width) as i64;
    let mut layer_best = best.to_vec();
    // Per column, what a later layer may not take: the rows near the edgels kept so far and, where
    // nothing is kept yet, every earlier layer's candidate (it failed to chain; offer the next one).
    // Where an edgel is kept, an earlier layer's candidate is offered again: the column's strongest
    // candidate may have lain on a second wall and lost its chain to the first wall followed through
    // from its neighbours (two walls of similar strength trade the top rank from column to column).
    let mut offered: Vec<Vec<u32>> = vec![Vec::new(); width];
    let mut kept_rows: Vec<Vec<i64>> = vec![Vec::new(); width];
    for layer in 0..selection.layers.max(1) {
        let before = out.len();
        chain_layer(
            &layer_best,
            &ranked,
            columns,
            width,
            selection,
            [floor, weak_floor],
            out,
        );
        if layer + 1 >= selection.layers {
            break;
        }
        for e in &out[before..] {
            kept_rows[e.index as usize % width].push(row(e));
        }
        let gap = selection.layer_gap_rows as i64;
        let mut any = false;
        for u in 0..width {
            if let Some(b) = layer_best[u] {
                offered[u].push(b.index);
            }
            layer_best[u] = columns[u]
                .iter()
                .filter(|e| {
                    (!kept_rows[u].is_empty() || !offered[u].contains(&e.index))
                        && kept_rows[u].iter().all(|&r| (row(e) - r).abs() > gap)
                })
                .min_by(|a, b| strongest_first(a, b))
                .copied();
            any |= layer_best[u].is_some();
        }
        if !any {
            break;
        }
        ranked = strongest_m(&layer_best, selection.count);
    }
    out.sort_unstable_by_key(|e| e.index);
    out.dedup_by_key(|e| e.index);
    reference
}

/// The M (`count`) strongest of the columns' candidates, strongest first.
fn strongest_m(best: &[Option<Edgel>], count: usize) -> Vec<Edgel> {
    let mut ranked: Vec<Edgel> = best.iter().flatten().copied().collect();
    ranked.sort_unstable_by(strongest_first);
    ranked.truncate(count);
    ranked
}

/// One layer of [`chained_column_edgels`]: the M strongest of `best` (`ranked`), kept where they chain
/// (runs of neighbouring columns within `link_rows` rows holding an edgel at or above `floors[0]`,
/// edgels down to `floors[1]`), and the run ends followed beyond where the column's strongest candidate
/// lies elsewhere.
fn chain_layer(
    best: &[Option<Edgel>],
    ranked: &[Edgel],
    columns: &[Vec<Edgel>],
    width: usize,
    selection: &EdgelSelection,
    [floor, weak_floor]: [f32; 2],
    out: &mut Vec<Edgel>,
) {
    // Columns whose candidate survived the M cut.
    let mut in_m = vec![false; width];
    for e in ranked {
        in_m[e.index as usize % width] = true;
    }
    let candidate = |u: usize| best[u].filter(|e| in_m[u] && e.strength >= weak_floor);
    let row = |e: &Edgel| (e.index as usize / width) as i64;
    // Runs of consecutive columns whose candidates are within `link_rows` rows of each other.
    let mut u = 0;
    while u < width {
        let Some(first) = candidate(u) else {
            u += 1;
            continue;
        };
        let start = u;
        let mut strong = first.strength >= floor;
        let mut prev = first;
        u += 1;
        while u < width {
            match candidate(u) {
                Some(e)
                    if (row(&e) - row(&prev)).unsigned_abs() as usize <= selection.link_rows =>
                {
                    strong |= e.strength >= floor;
                    prev = e;
                    u += 1;
                }
                _ => break,
            }
        }
        if strong && u - start >= selection.min_chain_columns {
            out.extend(
                (start..u)
                    .filter_map(candidate)
                    .filter(|e| selection.link_rows > 0 || e.strength >= floor),
            );
            if selection.link_rows > 0 {
                // Follow the boundary beyond the run's ends where the column's strongest candidate lies
                // elsewhere: the strongest candidate linked to the last edgel, while one is above the weak floor.
                for (from, step) in [(start, -1i64), (u - 1, 1i64)] {
                    let mut prev = candidate(from).expect("run ends hold candidates");
                    let mut c = from as i64 + step;
                    while c >= 0 && (c as usize) < width {
                        let next = columns[c as usize]
                            .iter()
                            .filter(|e| {
                                e.strength >= weak_floor
                                    && (row(e) - row(&prev)).unsigned_abs() as usize
                                        <= selection.link_rows
                            })
                            .min_by(|a, b| strongest_first(a, b));
                        let Some(&e) = next else { break };
                        out.push(e);
                        prev = e;
                        c += step;
                    }
                }
            }
        }
    }
}

/// Squared Euclidean distance (in px^2, exact integers) from every pixel to the nearest seed, computed
/// exactly up to `cap_px` and reported as at least `cap_px^2` beyond it (the callers only need distances
/// inside the likelihood's truncation radius). Felzenszwalb & Huttenlocher's lower envelope per row
/// after a column pass. `seeds` are row-major indices.
pub fn squared_distance_capped(
    seeds: impl Iterator<Item = usize>,
    width: usize,
    height: usize,
    cap_px: u32,
    column: &mut Vec<u32>,
    out: &mut Vec<f32>,
) {
    let n = width * height;
    let cap = cap_px.max(1);
    column.clear();
    column.resize(n, cap);
    out.resize(n, 0.0);
    if n == 0 {
        return;
    }
    for s in seeds {
        column[s] = 0;
    }
    // Column distances: forward then backward sweep, row by row (contiguous, vectorisable).
    for v in 1..height {
        let (above, here) = column.split_at_mut(v * width);
        let above = &above[(v - 1) * width..];
        for (h, a) in here[..width].iter_mut().zip(above) {
            *h = (*h).min(a + 1).min(cap);
        }
    }
    for v in (0..height - 1).rev() {
        let (here, below) = column.split_at_mut((v + 1) * width);
        let here = &mut here[v * width..];
        for (h, b) in here.iter_mut().zip(&below[..width]) {
            *h = (*h).min(b + 1).min(cap);
        }
    }
    let column_ref: &[u32] = column;
    out.par_chunks_mut(width).enumerate().for_each_init(
        || (vec![0usize; width], vec![0f32; width + 1]),
        |(hull, bounds), (v, dst)| {
            let f = |q: usize| {
                let d = column_ref[v * width + q] as f32;
                d * d
            };
            lower_envelope(width, f, hull, bounds, dst);
        },
    );
}

/// 1D squared distance transform of sampled function `f` over 0..n (Felzenszwalb & Huttenlocher 2012).
fn lower_envelope(
    n: usize,
    f: impl Fn(usize) -> f32,
    hull: &mut [usize],
    bounds: &mut [f32],
    dst: &mut [f32],
) {
    let mut k = 0usize;
    hull[0] = 0;
    bounds[0] = f32::NEG_INFINITY;
    bounds[1] = f32::INFINITY;
    let fq_plus = |q: usize| f(q) + (q * q) as f32;
    for q in 1..n {
        // bounds[0] is -inf, so the loop stops at k = 0 at the latest.
        let mut s = (fq_plus(q) - fq_plus(hull[k])) / (2.0 * (q as f32 - hull[k] as f32));
        while s <= bounds[k] {
            k -= 1;
            s = (fq_plus(q) - fq_plus(hull[k])) / (2.0 * (q as f32 - hull[k] as f32));
        }
        k += 1;
        hull[k] = q;
        bounds[k] = s;
        bounds[k + 1] = f32::INFINITY;
    }
    let mut k = 0usize;
    for (x, d) in dst.iter_mut().enumerate().take(n) {
        while bounds[k + 1] < x as f32 {
            k += 1;
        }
        let p = hull[k];
        let dx = x as f32 - p as f32;
        *d = dx * dx + f(p);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute-force reference for the distance transform.
    fn brute(seeds: &[usize], w: usize, h: usize, cap: u32) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (u, v) = ((i % w) as i64, (i / w) as i64);
                let best = seeds
                    .iter()
                    .map(|&s| {
                        let (su, sv) = ((s % w) as i64, (s / w) as i64);
                        ((u - su).pow(2) + (v - sv).pow(2)) as f32
                    })
                    .fold(f32::INFINITY, f32::min);
                best.min((cap * cap) as f32)
            })
            .collect()
    }

    #[test]
    fn distance_transform_matches_brute_force_below_cap() {
        let (w, h, cap) = (37, 23, 9);
        let seeds = [5usize, 100, 101, 400, 777, 850];
        let mut col = Vec::new();
        let mut out = Vec::new();
        squared_distance_capped(seeds.iter().copied(), w, h, cap, &mut col, &mut out);
        let reference = brute(&seeds, w, h, cap);
        for i in 0..w * h {
            let capped = out[i].min((cap * cap) as f32);
            // Exact below the cap (all quantities are small integers in f32); at least cap^2 beyond.
            if reference[i] < (cap * cap) as f32 {
                assert_eq!(capped, reference[i], "pixel {i}");
            } else {
                assert!(out[i] >= (cap * cap) as f32, "pixel {i}");
            }
        }
    }

    #[test]
    fn distance_transform_without_seeds_is_at_cap() {
        let mut col = Vec::new();
        let mut out = Vec::new();
        squared_distance_capped(std::iter::empty(), 8, 6, 5, &mut col, &mut out);
        assert!(out.iter().all(|&d| d >= 25.0));
    }

    #[test]
    fn smoothing_preserves_constants_and_mass_of_an_impulse() {
        let (w, h) = (31, 29);
        let taps = gaussian_taps(2.0);
        let mut tmp = Vec::new();
        let mut out = Vec::new();
        smooth(&vec![7.0; w * h], w, h, &taps, &mut tmp, &mut out);
        assert!(out.iter().all(|&x| (x - 7.0).abs() < 1e-4));
        let mut impulse = vec![0.0; w * h];
        impulse[15 * w + 15] = 1.0;
        smooth(&impulse, w, h, &taps, &mut tmp, &mut out);
        let sum: f32 = out.iter().sum();
        assert!((sum - 1.0).abs() < 1e-5, "mass {sum}");
        // Symmetric and peaked at the impulse.
        assert_eq!(out[15 * w + 14], out[15 * w + 16]);
        assert_eq!(out[14 * w + 15], out[16 * w + 15]);
        assert!(out[15 * w + 15] > out[15 * w + 16]);
    }

    /// `img` (w x h) smoothed with a Gaussian of `sigma_px`.
    fn smoothed(img: &[f32], w: usize, h: usize, sigma_px: f64) -> Vec<f32> {
        let (mut tmp, mut out) = (Vec::new(), Vec::new());
        smooth(img, w, h, &gaussian_taps(sigma_px), &mut tmp, &mut out);
        out
    }

    fn sel(count: usize, polarity: EdgePolarity) -> EdgelSelection {
        EdgelSelection {
            count,
            min_strength: 0.0,
            relative_floor: 0.0,
            reference_at_least: 0.0,
            polarity,
            per_column: false,
            weak_fraction: 1.0,
            link_rows: 0,
            min_chain_columns: 0,
            layers: 1,
            layer_gap_rows: 0,
        }
    }

    #[test]
    fn edgels_sit_on_a_horizontal_step_one_per_column() {
        let (w, h) = (12, 20);
        let img: Vec<f32> = (0..w * h)
            .map(|i| if i / w >= 10 { 100.0 } else { 0.0 })
            .collect();
        let s = smoothed(&img, w, h, 1.5);
        let mut edgels = Vec::new();
        strongest_column_edgels(&s, w, h, &sel(100, EdgePolarity::Rising), &mut edgels);
        assert_eq!(edgels.len(), w);
        for e in &edgels {
            let v = e.index as usize / w;
            assert!(v == 9 || v == 10, "edgel at row {v}");
        }
        strongest_column_edgels(&s, w, h, &sel(5, EdgePolarity::Rising), &mut edgels);
        assert_eq!(edgels.len(), 5);
        strongest_column_edgels(&s, w, h, &sel(100, EdgePolarity::Falling), &mut edgels);
        assert!(edgels.is_empty());
        strongest_column_edgels(&s, w, h, &sel(100, EdgePolarity::Both), &mut edgels);
        assert_eq!(edgels.len(), w);
    }

    /// Chained edgels in one layer: floor 0.35, hysteresis to 0.3 of it over 3 rows, chains of 8 columns.
    fn chained_selection(count: usize) -> EdgelSelection {
        EdgelSelection {
            count,
            min_strength: 0.0,
            relative_floor: 0.35,
            reference_at_least: 0.0,
            polarity: EdgePolarity::Rising,
            per_column: true,
            weak_fraction: 0.3,
            link_rows: 3,
            min_chain_columns: 8,
            layers: 1,
            layer_gap_rows: 0,
        }
    }

    #[test]
    fn a_second_layer_chains_a_wall_behind_the_first() {
        // Two rising steps down every column: a strong one at row 10 and a weaker one at row 30.
        let (w, h) = (40, 45);
        let img: Vec<f32> = (0..w * h)
            .map(|i| match i / w {
                v if v >= 30 => 160.0,
                v if v >= 10 => 100.0,
                _ => 0.0,
            })
            .collect();
        let s = smoothed(&img, w, h, 1.0);
        let one = EdgelSelection {
            layer_gap_rows: 8,
            ..chained_selection(w)
        };
        let rows = |edgels: &[Edgel]| -> Vec<usize> {
            let mut r: Vec<usize> = edgels.iter().map(|e| e.index as usize / w).collect();
            r.sort_unstable();
            r.dedup();
            r
        };
        let mut edgels = Vec::new();
        strongest_column_edgels(&s, w, h, &one, &mut edgels);
        assert_eq!(edgels.len(), w);
        assert!(
            rows(&edgels).iter().all(|r| (9..=10).contains(r)),
            "{edgels:?}"
        );
        let two = EdgelSelection { layers: 2, ..one };
        strongest_column_edgels(&s, w, h, &two, &mut edgels);
        assert_eq!(edgels.len(), 2 * w);
        assert!(
            rows(&edgels)
                .iter()
                .all(|r| (9..=10).contains(r) || (29..=30).contains(r)),
            "{edgels:?}"
        );
        // Within the gap of the first layer's edgels nothing more is taken.
        let close = EdgelSelection {
            layer_gap_rows: 25,
            ..two
        };
        strongest_column_edgels(&s, w, h, &close, &mut edgels);
        assert_eq!(edgels.len(), w);
    }

    #[test]
    fn a_second_layer_takes_the_wall_that_lost_its_columns_to_the_first() {
        // A step at row 10 across the frame and, over the right half, a second one at row 30 that is
        // stronger than the first in every other block of 4 columns and weaker in the rest: each column's
        // strongest candidate alternates between the walls, so neither forms a chain in the first layer
        // there; the first wall is followed through from its run on the left.
        let (w, h) = (60, 45);
        let img: Vec<f32> = (0..w * h)
            .map(|i| {
                let (u, v) = (i % w, i / w);
                let floor = if (u / 4) % 2 == 0 { 130.0 } else { 70.0 };
                match v {
                    v if v >= 30 && u >= 30 => 100.0 + floor,
                    v if v >= 10 => 100.0,
                    _ => 0.0,
                }
            })
            .collect();
        let s = smoothed(&img, w, h, 1.0);
        let two = EdgelSelection {
            layers: 2,
            layer_gap_rows: 8,
            ..chained_selection(w)
        };
        let mut edgels = Vec::new();
        strongest_column_edgels(&s, w, h, &two, &mut edgels);
        let at = |rows: std::ops::RangeInclusive<usize>| -> Vec<usize> {
            edgels
                .iter()
                .filter(|e| rows.contains(&(e.index as usize / w)))
                .map(|e| e.index as usize % w)
                .collect()
        };
        assert_eq!(at(9..=10), (0..w).collect::<Vec<_>>(), "{edgels:?}");
        // Every column of the second wall, including those whose strongest candidate it was (offered to
        // the first layer, not kept there); column 29 holds its edge blurred by the smoothing.
        let second = at(29..=30);
        assert!(
            (30..w).all(|u| second.contains(&u)) && second.iter().all(|&u| u >= 29),
            "{edgels:?}"
        );
        assert_eq!(edgels.len(), w + second.len());
    }

    #[test]
    fn chained_edgels_follow_a_fading_step_and_drop_short_speckle_chains() {
        // A step whose height fades from 100 to 10 across the columns, and a short strong blob.
        let (w, h) = (60, 40);
        let mut img = vec![0.0f32; w * h];
        for v in 0..h {
            for u in 0..w {
                if v >= 20 {
                    img[v * w + u] = 100.0 - 90.0 * u as f32 / (w - 1) as f32;
                }
            }
        }
        for v in 6..h.min(9) {
            for u in 40..43 {
                img[v * w + u] = 150.0;
            }
        }
        let s = smoothed(&img, w, h, 1.0);
        let chained = chained_selection(w);
        let mut edgels = Vec::new();
        strongest_column_edgels(&s, w, h, &chained, &mut edgels);
        let on_step = |e: &Edgel| (19..=20).contains(&(e.index as usize / w));
        // Every column of the step, including its faint end, and nothing of the 3-column blob.
        assert!(edgels.iter().all(on_step), "{edgels:?}");
        assert_eq!(edgels.len(), w);
        // Without hysteresis the faint end falls below the floor.
        let plain = EdgelSelection {
            weak_fraction: 1.0,
            ..chained
        };
        strongest_column_edgels(&s, w, h, &plain, &mut edgels);
        assert!(edgels.len() < w - 10, "{}", edgels.len());
    }
}
