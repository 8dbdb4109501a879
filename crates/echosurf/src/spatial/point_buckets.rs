//! Points in a uniform bucket grid (buckets sorted by their packed cell key), shared by the stages: "is
//! this point within `radius` of any data point?" (the surfacing's region of trust) and "every point
//! within `radius`" (the oriented-point sheet, and which echoes back a mesh piece).

use glam::DVec3;

use super::cell_grid::{CELL_AXIS_MAX, pack_cell, unpack_cell};

/// Points bucketed into cubes of side `radius`: a query looks at the 27 buckets around the point.
/// Points are stored sorted by bucket key, so the structure is two flat arrays.
#[derive(Debug, Clone)]
pub struct PointBuckets {
    radius_mm: f64,
    origin_mm: DVec3,
    /// Sorted bucket keys, one per non-empty bucket, and where its points start in `points`.
    bucket_keys: Vec<u64>,
    bucket_starts: Vec<u32>,
    points: Vec<DVec3>,
    /// Index of each (sorted) point in the caller's slice.
    original: Vec<u32>,
    /// Where each (y, z) row of buckets starts in `bucket_keys`, when the grid is compact enough.
    rows: Option<RowIndex>,
}

/// The first bucket of every (y, z) row of a grid whose bucket coordinates start at zero:
/// `starts[z * rows_y + y]` up to the next entry. A query searches its row's few buckets instead of
/// all the keys.
#[derive(Debug, Clone)]
struct RowIndex {
    rows_y: i64,
    rows_z: i64,
    starts: Vec<u32>,
}

/// A row index is built when it has at most this many rows per non-empty bucket (plus a few
/// thousand): points spread thinly over a large box search all the sorted keys instead.
const MAX_ROWS_PER_BUCKET: usize = 8;

impl RowIndex {
    fn new(bucket_keys: &[u64]) -> Option<RowIndex> {
        let (mut rows_y, mut rows_z) = (0i64, 0i64);
        for &k in bucket_keys {
            let [_, y, z] = unpack_cell(k);
            rows_y = rows_y.max(y as i64 + 1);
            rows_z = rows_z.max(z as i64 + 1);
        }
        let rows = rows_y as u128 * rows_z as u128;
        if rows > (MAX_ROWS_PER_BUCKET * bucket_keys.len() + 4096) as u128 {
            return None;
        }
        let rows = rows as usize;
        let mut starts = vec![0u32; rows + 1];
        for &k in bucket_keys {
            let [_, y, z] = unpack_cell(k);
            starts[(z as i64 * rows_y + y as i64) as usize + 1] += 1;
        }
        for r in 0..rows {
            starts[r + 1] += starts[r];
        }
        Some(RowIndex {
            rows_y,
            rows_z,
            starts,
        })
    }

    /// The buckets of row (y, z), both at least zero (empty outside the grid).
    fn row(&self, y: i64, z: i64) -> std::ops::Range<usize> {
        if y >= self.rows_y || z >= self.rows_z {
            return 0..0;
        }
        let r = (z * self.rows_y + y) as usize;
        self.starts[r] as usize..self.starts[r + 1] as usize
    }
}

impl PointBuckets {
    /// `None` when there are no (finite) trust points: no clipping. Bucket coordinates beyond the cell
    /// grid's `CELL_AXIS_MAX` are clamped (they only merge far buckets, which stays correct since
    /// points are compared exactly).
    pub fn new(points: &[DVec3], radius_mm: f64) -> Option<PointBuckets> {
        let finite: Vec<(u32, DVec3)> = points
            .iter()
            .enumerate()
            .filter(|(_, p)| p.is_finite())
            .map(|(i, &p)| (i as u32, p))
            .collect();
        if finite.is_empty() {
            return None;
        }
        let origin_mm = finite
            .iter()
            .fold(DVec3::splat(f64::INFINITY), |a, (_, p)| a.min(*p));
        let mut region = PointBuckets {
            radius_mm,
            origin_mm,
            bucket_keys: Vec::new(),
            bucket_starts: Vec::new(),
            points: Vec::new(),
            original: Vec::new(),
            rows: None,
        };
        let mut keyed: Vec<(u64, u32, DVec3)> = finite
            .iter()
            .map(|&(i, p)| (region.key(region.bucket(p)), i, p))
            .collect();
        keyed.sort_by_key(|&(k, i, _)| (k, i));
        for (i, (k, original, p)) in keyed.iter().enumerate() {
            if region.bucket_keys.last() != Some(k) {
                region.bucket_keys.push(*k);
                region.bucket_starts.push(i as u32);
            }
            region.points.push(*p);
            region.original.push(*original);
        }
        region.bucket_starts.push(keyed.len() as u32);
        region.rows = RowIndex::new(&region.bucket_keys);
        Some(region)
    }

    fn bucket(&self, p: DVec3) -> [i64; 3] {
        let q = (p - self.origin_mm) / self.radius_mm;
        [q.x, q.y, q.z].map(|c| (c.floor() as i64).clamp(0, CELL_AXIS_MAX))
    }

    fn key(&self, b: [i64; 3]) -> u64 {
        pack_cell(b.map(|c| c as i32))
    }

    /// Whether some trust point lies within the radius of `p` (inclusive).
    pub fn contains(&self, p: DVec3) -> bool {
        let mut found = false;
        self.visit_within(p, self.radius_mm, |_, _| {
            found = true;
            false
        });
        found
    }

    /// Calls `f(index, point)` for every point within `reach_mm` (at most the bucket radius) of `p`,
    /// `index` being its position in the slice given to [`PointBuckets::new`], in bucket order, until `f`
    /// returns false.
    pub fn visit_within(&self, p: DVec3, reach_mm: f64, mut f: impl FnMut(usize, DVec3) -> bool) {
        let r2 = reach_mm.min(self.radius_mm).powi(2);
        let mut go_on = true;
        self.runs_around(p, |run| {
            for k in run {
                let t = self.points[k];
                if t.distance_squared(p) <= r2 && !f(self.original[k] as usize, t) {
                    go_on = false;
                    break;
                }
            }
            go_on
        });
    }

    /// Calls `f(run)` with the range (into [`PointBuckets::sorted_points`]) of each non-empty (y, z) row of
    /// three x-buckets around `p`, in the order [`PointBuckets::visit_within`] visits them, until `f`
    /// returns false: every point within the bucket radius of `p` is in one of them. The three buckets
    /// along x of one row have consecutive keys, so their points are one contiguous run: one search per
    /// row instead of one per bucket.
    pub fn runs_around(&self, p: DVec3, mut f: impl FnMut(std::ops::Range<usize>) -> bool) {
        let q = (p - self.origin_mm) / self.radius_mm;
        // Entirely below the origin by more than one bucket: nothing can be near.
        if !p.is_finite() || q.min_element() < -1.0 {
            return;
        }
        let b = self.bucket(p);
        let x_lo = (b[0] - 1).max(0);
        let x_hi = (b[0] + 1).min(CELL_AXIS_MAX);
        for dz in -1..=1 {
            for dy in -1..=1 {
                let (y, z) = (b[1] + dy, b[2] + dz);
                if !(0..=CELL_AXIS_MAX).contains(&y) || !(0..=CELL_AXIS_MAX).contains(&z) {
                    continue;
                }
                let (lo, hi) = (self.key([x_lo, y, z]), self.key([x_hi, y, z]));
                let row = match &self.rows {
                    Some(rows) => rows.row(y, z),
                    None => 0..self.bucket_keys.len(),
                };
                let keys = &self.bucket_keys[row.clone()];
                let first = keys.partition_point(|&k| k < lo);
                let last = row.start + first + keys[first..].partition_point(|&k| k <= hi);
                let first = row.start + first;
                if first == last {
                    continue;
                }
                let run = self.bucket_starts[first] as usize..self.bucket_starts[last] as usize;
                if !f(run) {
                    return;
                }
            }
        }
    }

    /// The (finite) points in bucket order: the ranges of [`PointBuckets::runs_around`] index them.
    pub fn sorted_points(&self) -> &[DVec3] {
        &self.points
    }

    /// Each sorted point's index in the slice given to [`PointBuckets::new`].
    pub fn original_indices(&self) -> &[u32] {
        &self.original
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// `n` points uniform in the cube [-below, side - below]^3 (mm).
    fn random_points(rng: &mut impl Rng, n: usize, side: f64, below: f64) -> Vec<DVec3> {
        (0..n)
            .map(|_| DVec3::new(rng.random(), rng.random(), rng.random()) * side - below)
            .collect()
    }

    #[test]
    fn matches_brute_force() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let pts = random_points(&mut rng, 300, 20.0, 5.0);
        let region = PointBuckets::new(&pts, 1.5).unwrap();
        for _ in 0..2000 {
            let q = DVec3::new(rng.random(), rng.random(), rng.random()) * 30.0 - 10.0;
            let brute = pts.iter().any(|p| p.distance(q) <= 1.5);
            assert_eq!(region.contains(q), brute, "{q}");
        }
        assert!(PointBuckets::new(&[], 1.0).is_none());
        // Neighbour visits: exactly the points within reach, by their index in `pts`.
        for _ in 0..200 {
            let q = DVec3::new(rng.random(), rng.random(), rng.random()) * 30.0 - 10.0;
            let mut seen = Vec::new();
            region.visit_within(q, 1.2, |i, p| {
                assert_eq!(p, pts[i]);
                seen.push(i);
                true
            });
            seen.sort_unstable();
            let brute: Vec<usize> = (0..pts.len())
                .filter(|&i| pts[i].distance(q) <= 1.2)
                .collect();
            assert_eq!(seen, brute);
        }
    }

    #[test]
    fn points_spread_thinly_over_a_large_box_are_found_without_the_row_index() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        // Two clusters 50 m apart: their rows would outnumber the buckets by far.
        let mut pts = random_points(&mut rng, 200, 6.0, 0.0);
        pts.extend(random_points(&mut rng, 200, 6.0, -50_000.0));
        let spread = PointBuckets::new(&pts, 0.5).unwrap();
        assert!(spread.rows.is_none());
        let compact = PointBuckets::new(&pts[..200], 0.5).unwrap();
        assert!(compact.rows.is_some());
        for _ in 0..2000 {
            let near = DVec3::new(rng.random(), rng.random(), rng.random()) * 7.0 - 0.5;
            for q in [near, near + 50_000.0] {
                let brute = pts.iter().any(|p| p.distance(q) <= 0.5);
                assert_eq!(spread.contains(q), brute, "{q}");
            }
            let brute = pts[..200].iter().any(|p| p.distance(near) <= 0.5);
            assert_eq!(compact.contains(near), brute, "{near}");
        }
    }

    #[test]
    fn runs_around_cover_the_points_visit_within_visits_in_its_order() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let pts = random_points(&mut rng, 400, 12.0, 3.0);
        let region = PointBuckets::new(&pts, 1.5).unwrap();
        let (sorted, original) = (region.sorted_points(), region.original_indices());
        for (&p, &i) in sorted.iter().zip(original) {
            assert_eq!(p, pts[i as usize]);
        }
        for _ in 0..500 {
            let q = DVec3::new(rng.random(), rng.random(), rng.random()) * 18.0 - 6.0;
            // Every point of the runs, in their order; with the radius as reach, visit_within's filter
            // keeps exactly those within it, in the same order.
            let mut in_runs = Vec::new();
            region.runs_around(q, |run| {
                in_runs.extend(run);
                true
            });
            let mut visited = Vec::new();
            region.visit_within(q, 1e9, |i, _| {
                visited.push(i);
                true
            });
            let within: Vec<usize> = in_runs
                .iter()
                .filter(|&&k| sorted[k].distance_squared(q) <= 1.5f64.powi(2))
                .map(|&k| original[k] as usize)
                .collect();
            assert_eq!(within, visited);
            // The runs hold every point within the radius, each once.
            let mut unique = in_runs.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(unique.len(), in_runs.len());
            let brute = (0..pts.len())
                .filter(|&i| pts[i].distance(q) <= 1.5)
                .count();
            assert_eq!(within.len(), brute);
        }
    }
}
