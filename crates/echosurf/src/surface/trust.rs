//! Region of trust: "is this point within `radius` of any data point?" via a uniform bucket grid.

use glam::DVec3;

/// Trust points bucketed into cubes of side `radius`: a query looks at the 27 buckets around the point.
/// Points are stored sorted by bucket key, so the structure is two flat arrays.
#[derive(Debug, Clone)]
pub(crate) struct TrustRegion {
    radius_mm: f64,
    origin_mm: DVec3,
    /// Sorted bucket keys, one per non-empty bucket, and where its points start in `points`.
    bucket_keys: Vec<u64>,
    bucket_starts: Vec<u32>,
    points: Vec<DVec3>,
}

const BUCKET_BITS: u32 = 21;
const BUCKET_MAX: i64 = (1 << BUCKET_BITS) - 1;

impl TrustRegion {
    /// `None` when there are no (finite) trust points: no clipping. Bucket coordinates beyond 2^21 are
    /// clamped (they only merge far buckets, which stays correct since points are compared exactly).
    pub fn new(points: &[DVec3], radius_mm: f64) -> Option<TrustRegion> {
        let finite: Vec<DVec3> = points.iter().copied().filter(|p| p.is_finite()).collect();
        if finite.is_empty() {
            return None;
        }
        let origin_mm = finite
            .iter()
            .fold(DVec3::splat(f64::INFINITY), |a, p| a.min(*p));
        let mut region = TrustRegion {
            radius_mm,
            origin_mm,
            bucket_keys: Vec::new(),
            bucket_starts: Vec::new(),
            points: Vec::new(),
        };
        let mut keyed: Vec<(u64, DVec3)> = finite
            .iter()
            .map(|&p| (region.key(region.bucket(p)), p))
            .collect();
        keyed.sort_by(|a, b| {
            a.0.cmp(&b.0)
                .then(a.1.to_array().partial_cmp(&b.1.to_array()).unwrap())
        });
        for (i, (k, p)) in keyed.iter().enumerate() {
            if region.bucket_keys.last() != Some(k) {
                region.bucket_keys.push(*k);
                region.bucket_starts.push(i as u32);
            }
            region.points.push(*p);
        }
        region.bucket_starts.push(keyed.len() as u32);
        Some(region)
    }

    fn bucket(&self, p: DVec3) -> [i64; 3] {
        let q = (p - self.origin_mm) / self.radius_mm;
        [q.x, q.y, q.z].map(|c| (c.floor() as i64).clamp(0, BUCKET_MAX))
    }

    fn key(&self, b: [i64; 3]) -> u64 {
        b[0] as u64 | (b[1] as u64) << BUCKET_BITS | (b[2] as u64) << (2 * BUCKET_BITS)
    }

    /// Whether some trust point lies within the radius of `p` (inclusive).
    pub fn contains(&self, p: DVec3) -> bool {
        let r2 = self.radius_mm * self.radius_mm;
        let q = (p - self.origin_mm) / self.radius_mm;
        // Entirely below the origin by more than one bucket: nothing can be near.
        if q.min_element() < -1.0 {
            return false;
        }
        let b = self.bucket(p);
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let n = [b[0] + dx, b[1] + dy, b[2] + dz];
                    if n.iter().any(|&c| !(0..=BUCKET_MAX).contains(&c)) {
                        continue;
                    }
                    if let Ok(i) = self.bucket_keys.binary_search(&self.key(n)) {
                        let range =
                            self.bucket_starts[i] as usize..self.bucket_starts[i + 1] as usize;
                        if self.points[range]
                            .iter()
                            .any(|t| t.distance_squared(p) <= r2)
                        {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn matches_brute_force() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let pts: Vec<DVec3> = (0..300)
            .map(|_| DVec3::new(rng.random(), rng.random(), rng.random()) * 20.0 - 5.0)
            .collect();
        let region = TrustRegion::new(&pts, 1.5).unwrap();
        for _ in 0..2000 {
            let q = DVec3::new(rng.random(), rng.random(), rng.random()) * 30.0 - 10.0;
            let brute = pts.iter().any(|p| p.distance(q) <= 1.5);
            assert_eq!(region.contains(q), brute, "{q}");
        }
        assert!(TrustRegion::new(&[], 1.0).is_none());
    }
}
