//! End-to-end checks of the surfacer on analytic fields with known surfaces.

use glam::DVec3;
use proptest::prelude::*;
use rand::SeedableRng;

use super::*;
use crate::mesh::MeshTopology;

const CENTRE: DVec3 = DVec3::new(0.13, -0.21, 0.07);

/// Higher inside (like the bright band), so normals point outward.
fn sphere(centre: DVec3, radius: f64) -> impl Fn(DVec3) -> (f64, DVec3) + Sync {
    move |p: DVec3| {
        let d = p - centre;
        let r = d.length();
        (radius - r, -d / r.max(1e-300))
    }
}

fn domain(min: f64, max: f64) -> SurfaceDomain {
    SurfaceDomain {
        bounds_min_mm: DVec3::splat(min),
        bounds_max_mm: DVec3::splat(max),
        ..Default::default()
    }
}

fn extract(
    f: impl Fn(DVec3) -> (f64, DVec3) + Sync,
    levels: &[f64],
    domain: &SurfaceDomain,
) -> (Vec<Mesh>, SurfaceStats) {
    extract_surfaces_with_stats(&FnField(f), levels, domain, &SurfaceOptions::default()).unwrap()
}

/// Minimum interior angle of every triangle, degrees.
fn min_angles_deg(mesh: &Mesh) -> Vec<f64> {
    mesh.triangles
        .iter()
        .map(|t| {
            let p = t.map(|i| mesh.vertices[i as usize]);
            (0..3)
                .map(|k| {
                    let (a, b, c) = (p[k], p[(k + 1) % 3], p[(k + 2) % 3]);
                    (b - a).angle_between(c - a).to_degrees()
                })
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

#[derive(Debug)]
struct AngleStats {
    below_10: f64,
    below_20: f64,
    below_30: f64,
    mean: f64,
}

fn angle_stats(mesh: &Mesh) -> AngleStats {
    let a = min_angles_deg(mesh);
    let share = |t: f64| a.iter().filter(|&&x| x < t).count() as f64 / a.len() as f64;
    AngleStats {
        below_10: share(10.0),
        below_20: share(20.0),
        below_30: share(30.0),
        mean: a.iter().sum::<f64>() / a.len() as f64,
    }
}

/// Every face's winding normal agrees with the field normals at its corners (toward lower values).
fn faces_agree_with_normals(mesh: &Mesh) -> usize {
    mesh.triangles
        .iter()
        .filter(|t| {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
            let n = (b - a).cross(c - a);
            let vn: DVec3 = t.iter().map(|&i| mesh.normals[i as usize]).sum();
            n.dot(vn) <= 0.0
        })
        .count()
}

/// The same lattice the surfacer uses for `domain`, sampled for marching cubes.
fn marching_cubes_on_lattice(
    f: impl Fn(DVec3) -> (f64, DVec3),
    domain: &SurfaceDomain,
    h: f64,
) -> Mesh {
    let l = lattice::Lattice::new(domain.bounds_min_mm, domain.bounds_max_mm, h).unwrap();
    let dims = l.cells.map(|c| c as usize + 1);
    let mut values = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                values.push(f(l.node_position([i as i32, j as i32, k as i32])).0 as f32);
            }
        }
    }
    marching_cubes(&values, dims, l.origin_mm, DVec3::splat(h), 0.0).unwrap()
}

#[test]
fn sphere_is_accurate_closed_and_better_shaped_than_marching_cubes() {
    let radius = 8.0;
    let d = domain(-10.0, 10.0);
    let (meshes, stats) = extract(sphere(CENTRE, radius), &[0.0], &d);
    let mesh = &meshes[0];
    // 0.02 mm is the requirement; Newton on |x - c| converges to rounding, so this is not tight.
    let worst = mesh
        .vertices
        .iter()
        .map(|v| ((*v - CENTRE).length() - radius).abs())
        .fold(0.0, f64::max);
    assert!(worst < 0.02, "vertex {worst} mm off the sphere");
    let topo = mesh.topology();
    assert!(topo.is_closed_manifold(), "{topo:?}");
    assert_eq!(topo.euler_characteristic, 2);
    assert_eq!(topo.components, 1);
    assert_eq!(mesh.normals.len(), mesh.vertices.len());
    for (v, n) in mesh.vertices.iter().zip(&mesh.normals) {
        assert!(
            n.dot((*v - CENTRE).normalize()) > 0.999,
            "normal {n} at {v} is not outward"
        );
    }

    let mc = marching_cubes_on_lattice(sphere(CENTRE, radius), &d, 0.5);
    let mc_topo = mc.topology();
    assert!(
        mc_topo.is_closed_manifold() && mc_topo.euler_characteristic == 2,
        "{mc_topo:?}"
    );
    assert_eq!(faces_agree_with_normals(&mc), 0);
    let ratio = mesh.triangles.len() as f64 / mc.triangles.len() as f64;
    let (rmt_angles, mc_angles) = (angle_stats(mesh), angle_stats(&mc));
    println!(
        "sphere r={radius} mm at 0.5 mm: RMT {} triangles ({} raw MT), MC {} triangles, ratio {ratio:.3}; \
         refused merges {}; nodes evaluated {}",
        mesh.triangles.len(),
        stats.levels[0].raw_triangles,
        mc.triangles.len(),
        stats.levels[0].refused_merges,
        stats.lattice_nodes_evaluated,
    );
    println!("min-angle RMT {rmt_angles:?}\nmin-angle MC  {mc_angles:?}");
    assert_eq!(
        faces_agree_with_normals(mesh),
        0,
        "winding disagrees with normals"
    );
    assert!(ratio <= 0.55, "triangle ratio {ratio}");
    assert!(rmt_angles.mean > mc_angles.mean);
    assert!(rmt_angles.below_10 < mc_angles.below_10);
    assert!(rmt_angles.below_20 < mc_angles.below_20);
    assert!(rmt_angles.below_30 < mc_angles.below_30);
}

fn assert_closed(topo: &MeshTopology, euler: i64, components: usize) {
    assert!(topo.is_closed_manifold(), "{topo:?}");
    assert_eq!(topo.euler_characteristic, euler, "{topo:?}");
    assert_eq!(topo.components, components, "{topo:?}");
}

#[test]
fn torus_has_euler_characteristic_zero() {
    let (major, minor) = (6.0, 2.0);
    let torus = move |p: DVec3| {
        let p = p - CENTRE;
        let q = (p.x * p.x + p.y * p.y).sqrt();
        let ring = DVec3::new(p.x, p.y, 0.0) * (major / q.max(1e-300));
        let d = p - ring;
        let r = d.length();
        (minor - r, -d / r.max(1e-300))
    };
    let (meshes, _) = extract(torus, &[0.0], &domain(-10.0, 10.0));
    assert_closed(&meshes[0].topology(), 0, 1);
    for v in &meshes[0].vertices {
        let p = *v - CENTRE;
        let q = (p.x * p.x + p.y * p.y).sqrt();
        let off = ((q - major).powi(2) + p.z * p.z).sqrt() - minor;
        assert!(off.abs() < 0.02, "{off}");
    }
}

/// Higher inside either sphere: the maximum of two sphere fields (its gradient is the winner's).
fn two_spheres(a: DVec3, b: DVec3, radius: f64) -> impl Fn(DVec3) -> (f64, DVec3) + Sync {
    move |p: DVec3| {
        let (fa, fb) = (sphere(a, radius)(p), sphere(b, radius)(p));
        if fa.0 >= fb.0 { fa } else { fb }
    }
}

#[test]
fn two_disjoint_spheres_give_two_components() {
    let (a, b) = (DVec3::new(-4.0, 0.1, 0.2), DVec3::new(4.3, -0.2, 0.0));
    let (meshes, _) = extract(two_spheres(a, b, 3.0), &[0.0], &domain(-9.0, 9.0));
    assert_closed(&meshes[0].topology(), 4, 2);
}

#[test]
fn surface_following_matches_the_full_grid_with_far_fewer_evaluations() {
    let radius = 5.0;
    let full_domain = domain(-10.0, 10.0);
    let (full, full_stats) = extract(sphere(CENTRE, radius), &[0.0], &full_domain);
    // Seeds: a point near the surface (its cell straddles) and one 0.7 mm off it (needs the search).
    let followed_domain = SurfaceDomain {
        seeds: vec![
            CENTRE + DVec3::new(radius + 0.1, 0.0, 0.0),
            CENTRE - DVec3::new(0.0, radius + 0.7, 0.0),
        ],
        ..full_domain.clone()
    };
    let (followed, stats) = extract(sphere(CENTRE, radius), &[0.0], &followed_domain);
    assert_eq!(followed[0].triangles.len(), full[0].triangles.len());
    assert_eq!(
        followed[0], full[0],
        "same cells, same order: identical meshes"
    );
    println!(
        "lattice nodes evaluated: following {} vs full grid {}; evaluations per triangle {:.2}",
        stats.lattice_nodes_evaluated,
        full_stats.lattice_nodes_evaluated,
        stats.evaluations_per_triangle()
    );
    assert!(stats.lattice_nodes_evaluated * 5 < full_stats.lattice_nodes_evaluated);
    assert_eq!(stats.seed_cells, 2);

    // Dense seeds like a sweep's samples: 4000 points in a shell +-1.5 mm around the surface. Same
    // mesh; the thinning keeps the cost near that of a few seeds.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let shell_seeds: Vec<DVec3> = (0..4000)
        .map(|_| {
            use rand::Rng;
            let dir = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            CENTRE + dir * (radius + rng.random_range(-1.5..1.5))
        })
        .collect();
    let dense = SurfaceDomain {
        seeds: shell_seeds,
        ..full_domain.clone()
    };
    let (dense_mesh, dense_stats) = extract(sphere(CENTRE, radius), &[0.0], &dense);
    assert_eq!(dense_mesh[0], full[0]);
    println!(
        "4000 shell seeds: {} seed cells after thinning, {} lattice nodes evaluated",
        dense_stats.seed_cells, dense_stats.lattice_nodes_evaluated
    );
    assert!(dense_stats.lattice_nodes_evaluated < 4 * stats.lattice_nodes_evaluated);

    // A seed far from any surface finds nothing: no mesh, and no error.
    let lost = SurfaceDomain {
        seeds: vec![DVec3::splat(9.5)],
        ..full_domain
    };
    let (meshes, _) = extract(sphere(CENTRE, radius), &[0.0], &lost);
    assert!(meshes[0].is_empty());
}

#[test]
fn trust_region_clips_a_sheet_far_from_the_data() {
    // A sphere (the data) plus a plane sheet z = 7 far from it: higher below the plane's far side.
    let field = |p: DVec3| {
        let s = sphere(CENTRE, 4.0)(p);
        let plane = (p.z - 7.0, DVec3::Z);
        if s.0 >= plane.0 { s } else { plane }
    };
    let d = domain(-9.0, 9.0);
    let (unclipped, _) = extract(field, &[0.0], &d);
    let t = unclipped[0].topology();
    assert_eq!(t.components, 2, "{t:?}");
    assert!(t.boundary_edges > 0, "the sheet ends at the box");
    // Trust points on the sphere only.
    let mut trust_points = Vec::new();
    for i in 0..40 {
        for j in 0..20 {
            let (phi, theta) = (i as f64 * 0.157, (j as f64 + 0.5) * 0.157);
            trust_points.push(
                CENTRE
                    + 4.0
                        * DVec3::new(
                            theta.sin() * phi.cos(),
                            theta.sin() * phi.sin(),
                            theta.cos(),
                        ),
            );
        }
    }
    let clipped_domain = SurfaceDomain { trust_points, ..d };
    let (clipped, _) = extract(field, &[0.0], &clipped_domain);
    assert_closed(&clipped[0].topology(), 2, 1);
    assert!(clipped[0].vertices.iter().all(|v| v.z < 5.0));
}

#[test]
fn several_levels_give_one_mesh_each() {
    // Concentric shells of the same field: levels 0 and 3 are spheres of radius 8 and 5.
    let (meshes, stats) = extract(sphere(CENTRE, 8.0), &[0.0, 3.0], &domain(-10.0, 10.0));
    assert_eq!(meshes.len(), 2);
    for (mesh, radius) in meshes.iter().zip([8.0, 5.0]) {
        assert_closed(&mesh.topology(), 2, 1);
        let r: f64 = mesh
            .vertices
            .iter()
            .map(|v| (*v - CENTRE).length())
            .sum::<f64>()
            / mesh.vertices.len() as f64;
        assert!((r - radius).abs() < 0.01, "{r}");
    }
    assert_eq!(stats.levels.len(), 2);
}

#[test]
fn output_does_not_depend_on_the_thread_count() {
    let d = SurfaceDomain {
        seeds: vec![CENTRE + DVec3::new(5.0, 0.0, 0.0)],
        ..domain(-7.0, 7.0)
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| extract(sphere(CENTRE, 5.0), &[0.0], &d).0)
    };
    assert_eq!(run(1), run(3));
}

#[test]
fn bad_parameters_are_errors() {
    let f = FnField(sphere(CENTRE, 5.0));
    let d = domain(-7.0, 7.0);
    let ok = SurfaceOptions::default();
    assert!(extract_surfaces(&f, &[f64::NAN], &d, &ok).is_err());
    for bad in [
        SurfaceOptions {
            resolution_mm: -1.0,
            ..ok.clone()
        },
        SurfaceOptions {
            trust_distance_mm: 0.0,
            ..ok.clone()
        },
        SurfaceOptions {
            cluster_cell_factor: 0.0,
            ..ok.clone()
        },
        SurfaceOptions {
            surface_tolerance_mm: f64::INFINITY,
            ..ok.clone()
        },
    ] {
        assert!(extract_surfaces(&f, &[0.0], &d, &bad).is_err(), "{bad:?}");
    }
    assert!(extract_surfaces(&f, &[0.0], &domain(1.0, -1.0), &ok).is_err());
    // A full grid of 2000^3 nodes is refused before anything is allocated.
    assert!(matches!(
        extract_surfaces(&f, &[0.0], &domain(0.0, 1000.0), &ok),
        Err(Error::ResourceLimit(_))
    ));
    let nan_field = FnField(|_p: DVec3| (f64::NAN, DVec3::ZERO));
    assert!(extract_surfaces(&nan_field, &[0.0], &d, &ok).is_err());
    assert!(marching_cubes(&[0.0; 7], [2, 2, 2], DVec3::ZERO, DVec3::ONE, 0.0).is_err());
    assert!(marching_cubes(&[0.0; 8], [2, 2, 2], DVec3::ZERO, DVec3::ZERO, 0.0).is_err());
}

/// A random smooth field: a sum of 1-4 Gaussian blobs, the level between 0.2 and 0.8 of the peak.
fn gaussian_field(blobs: Vec<(DVec3, f64, f64)>) -> impl Fn(DVec3) -> (f64, DVec3) + Sync {
    move |p: DVec3| {
        let mut value = 0.0;
        let mut gradient = DVec3::ZERO;
        for &(c, sigma, weight) in &blobs {
            let d = p - c;
            let g = weight * (-d.length_squared() / (2.0 * sigma * sigma)).exp();
            value += g;
            gradient += -d / (sigma * sigma) * g;
        }
        (value, gradient)
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    #[test]
    fn random_smooth_fields_give_oriented_manifolds(
        blobs in proptest::collection::vec(
            ((-3.0..3.0f64, -3.0..3.0f64, -3.0..3.0f64), 0.8..2.0f64, 0.5..1.5f64), 1..5),
        level in 0.2..0.8f64,
        resolution in 0.35..0.6f64,
    ) {
        let blobs: Vec<(DVec3, f64, f64)> =
            blobs.into_iter().map(|((x, y, z), s, w)| (DVec3::new(x, y, z), s, w)).collect();
        let field = FnField(gaussian_field(blobs));
        let options = SurfaceOptions { resolution_mm: resolution, ..Default::default() };
        // The box holds every level set: the total weight is at most 6, so values fall below 0.2 beyond
        // sqrt(2 * 2^2 * ln 30) = 5.2 mm of the nearest centre, and centres lie within 5.2 mm of 0.
        let d = domain(-12.0, 12.0);
        let (meshes, stats) = extract_surfaces_with_stats(&field, &[level], &d, &options).unwrap();
        let topo = meshes[0].topology();
        prop_assert!(topo.is_closed_manifold() || topo.triangles == 0, "{:?} {:?}", topo, stats);
        prop_assert_eq!(topo.degenerate_triangles, 0);
        prop_assert_eq!(stats.levels[0].unconverged_vertices, 0);
        // Marching cubes on the same lattice is watertight too.
        let level_mc = marching_cubes_on_lattice(|p| { let (v, g) = field.0(p); (v - level, g) }, &d, resolution);
        let t = level_mc.topology();
        prop_assert!(t.is_closed_manifold() || t.triangles == 0, "MC {:?}", t);
    }
}

/// A field that may be undefined (NaN) somewhere, to check the surfacer's handling of it.
struct Confined<F> {
    inner: F,
    allow_nan: bool,
}

impl<F: Fn(DVec3) -> (f64, DVec3) + Sync> ScalarField for Confined<F> {
    fn values(&self, points: &[DVec3], out: &mut [f64]) {
        for (p, o) in points.iter().zip(out.iter_mut()) {
            *o = (self.inner)(*p).0;
        }
    }
    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]) {
        for i in 0..points.len() {
            (values[i], gradients[i]) = (self.inner)(points[i]);
        }
    }
    fn nan_means_undefined(&self) -> bool {
        self.allow_nan
    }
    fn values_are_pointwise(&self) -> bool {
        true
    }
}

#[test]
fn an_undefined_region_ends_the_surface_without_a_fake_crossing() {
    // The sphere's field, undefined for x > 0.5: the surface is the sphere's part with x < 0.5 (less
    // the cells touching the undefined region), open there, and nothing at the jump to NaN.
    let radius = 2.0;
    let ball = sphere(DVec3::ZERO, radius);
    let confined = move |p: DVec3| {
        if p.x > 0.5 {
            (f64::NAN, DVec3::NAN)
        } else {
            ball(p)
        }
    };
    for seeds in [Vec::new(), vec![DVec3::new(-radius, 0.0, 0.0)]] {
        let domain = SurfaceDomain {
            seeds,
            ..domain(-4.0, 4.0)
        };
        let field = Confined {
            inner: &confined,
            allow_nan: true,
        };
        let mesh = extract_surfaces(&field, &[0.0], &domain, &SurfaceOptions::default())
            .unwrap()
            .remove(0);
        let topo = mesh.topology();
        assert_eq!(topo.components, 1);
        assert!(
            topo.is_oriented_manifold() && topo.boundary_edges > 0,
            "{topo:?}"
        );
        // Projection onto the sphere moves rim vertices by the chord sagitta (h^2 / 8r = 0.016 mm).
        for v in &mesh.vertices {
            assert!(
                v.x <= 0.5 + 0.02 && (v.length() - radius).abs() < 1e-3,
                "{v}"
            );
        }
        // The open rim lies within a cell diagonal of the cut.
        assert!(mesh.vertices.iter().any(|v| v.x > 0.5 - 0.9));
        // The same NaN from a field that does not declare it is a numerical error.
        let strict = Confined {
            inner: &confined,
            allow_nan: false,
        };
        assert!(extract_surfaces(&strict, &[0.0], &domain, &SurfaceOptions::default()).is_err());
    }
}

#[test]
fn the_nearest_first_bracket_search_finds_the_one_batch_search_s_brackets() {
    // A wavy field, undefined for x > 2, whose "gradient" is a fixed tilt: the brackets fall on every
    // line and at every distance, and some starts find none.
    let wavy = |p: DVec3| -> (f64, DVec3) {
        let v = (3.0 * p.x).sin() * (2.0 * p.y).cos() + 0.4 * (5.0 * p.z).sin() + 0.1 * p.x;
        let v = if p.x > 2.0 { f64::NAN } else { v };
        (v, DVec3::new(0.3, -1.0, 0.2))
    };
    let field = Confined {
        inner: wavy,
        allow_nan: true,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let starts: Vec<DVec3> = (0..3000)
        .map(|_| {
            use rand::Rng;
            DVec3::new(rng.random(), rng.random(), rng.random()) * 6.0 - 3.0
        })
        .collect();
    for level in [0.0, 0.7, 1.3] {
        let mut counter = lattice::EvalCounter::default();
        let (v0, g0) = lattice::evaluate_gradients(&field, &starts, &mut counter);
        let line = |k: usize, d: usize| -> DVec3 {
            if d == 0 {
                g0[k].normalize_or_zero()
            } else {
                AXIS_LINES[d - 1]
            }
        };
        let search = BracketSearch {
            field: &field,
            level,
            starts: &starts,
            start_values: &v0,
            line: &line,
            spacing_mm: 0.4,
        };
        let (mut batch_count, mut nearest_count) = (counter, counter);
        let batch = search.in_one_batch(&mut batch_count);
        let nearest = search.nearest_first(&mut nearest_count);
        let bits = |b: &Brackets| -> Vec<Option<(usize, [u64; 4])>> {
            b.iter()
                .map(|f| f.map(|(d, (ta, va, tb, vb))| (d, [ta, va, tb, vb].map(f64::to_bits))))
                .collect()
        };
        assert_eq!(bits(&batch), bits(&nearest), "level {level}");
        // The cases are all there: every line, near and far brackets, and none.
        let lines: std::collections::BTreeSet<usize> =
            batch.iter().flatten().map(|&(d, _)| d).collect();
        assert_eq!(lines.len(), SEARCH_LINES, "level {level}: {lines:?}");
        let far = batch
            .iter()
            .flatten()
            .filter(|(_, b)| b.2.abs() >= 1.0)
            .count();
        assert!(far > 0, "level {level}");
        assert!(batch.iter().any(Option::is_none), "level {level}");
        assert!(
            nearest_count.gradients < batch_count.gradients,
            "level {level}: {} vs {}",
            nearest_count.gradients,
            batch_count.gradients
        );
    }
}
