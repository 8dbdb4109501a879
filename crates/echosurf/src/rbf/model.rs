//! The fitted model (a global spline or a partition-of-unity blend), its fast evaluation, and the
//! `.esrbf` file format.
//!
//! `.esrbf` (little-endian): magic `ESRBF\r\n\x1a`, u32 version, body, then a u64 FNV-1a hash of
//! everything before it. Version 1 (global spline): u64 centre count n, f64 smoothing, f64 eval_accuracy,
//! f64 origin[3], f64 c0, f64 c[3], then n x (f64 x, y, z), n x f64 coefficients. Version 2
//! (partition of unity): the body of `PuModel::encode`. Global models are still written as version 1.
//! Every size is checked against the file length before anything is allocated.

use std::io::Write;
use std::path::Path;
use std::sync::OnceLock;

use glam::DVec3;
use rayon::prelude::*;

use super::pu::PuModel;
use super::tree::{Tree, Treecode, TreecodeParams, sum_r, sum_r_grad};
use crate::error::FormatProblem;
use crate::{Error, Result};

const MAGIC: &[u8; 8] = b"ESRBF\r\n\x1a";
const VERSION: u32 = 1;
const PU_VERSION: u32 = 2;
const HEADER_BYTES: usize = 8 + 4 + 8 + 8 * 9;
/// Below this many kernel evaluations a direct sum is cheaper than building target trees.
const DIRECT_EVALUATION_LIMIT: usize = 4_000_000;

/// A fitted field: either the global biharmonic spline `s(x) = c0 + c.(x - origin) + sum_i l_i |x - x_i|`
/// or a partition-of-unity blend of local splines of that form (see `rbf::pu`).
#[derive(Clone)]
pub struct RbfModel {
    kind: ModelKind,
}

#[derive(Clone)]
enum ModelKind {
    Global(GlobalModel),
    PartitionOfUnity(PuModel),
}

/// The global spline `s(x) = c0 + c.(x - origin) + sum_i l_i |x - x_i|`.
pub(crate) struct GlobalModel {
    pub(crate) centres: Vec<DVec3>,
    pub(crate) coefficients: Vec<f64>,
    pub(crate) origin: DVec3,
    pub(crate) constant: f64,
    pub(crate) linear: DVec3,
    pub(crate) smoothing: f64,
    pub(crate) eval_accuracy: f64,
    fast: OnceLock<FastEvaluator>,
}

impl std::fmt::Debug for RbfModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.kind {
            ModelKind::Global(g) => g.fmt(f),
            ModelKind::PartitionOfUnity(pu) => f
                .debug_struct("RbfModel(partition of unity)")
                .field("points", &pu.points.len())
                .field("patches", &pu.patches())
                .field("local_centres", &pu.coefficients.len())
                .field("smoothing", &pu.smoothing)
                .finish(),
        }
    }
}

impl std::fmt::Debug for GlobalModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RbfModel")
            .field("centres", &self.centres.len())
            .field("origin", &self.origin)
            .field("constant", &self.constant)
            .field("linear", &self.linear)
            .field("smoothing", &self.smoothing)
            .field("eval_accuracy", &self.eval_accuracy)
            .finish()
    }
}

impl Clone for GlobalModel {
    fn clone(&self) -> Self {
        GlobalModel::new(
            self.centres.clone(),
            self.coefficients.clone(),
            self.origin,
            self.constant,
            self.linear,
            self.smoothing,
            self.eval_accuracy,
        )
    }
}

/// Source treecode with the model's coefficients already folded into proxy charges.
struct FastEvaluator {
    treecode: Treecode,
    charges: Vec<f64>,
    proxies: Vec<f64>,
}

impl RbfModel {
    pub(crate) fn new(
        centres: Vec<DVec3>,
        coefficients: Vec<f64>,
        origin: DVec3,
        constant: f64,
        linear: DVec3,
        smoothing: f64,
        eval_accuracy: f64,
    ) -> RbfModel {
        RbfModel {
            kind: ModelKind::Global(GlobalModel::new(
                centres,
                coefficients,
                origin,
                constant,
                linear,
                smoothing,
                eval_accuracy,
            )),
        }
    }

    pub(crate) fn from_partition_of_unity(model: PuModel) -> RbfModel {
        RbfModel {
            kind: ModelKind::PartitionOfUnity(model),
        }
    }

    pub(crate) fn partition_of_unity(&self) -> Option<&PuModel> {
        match &self.kind {
            ModelKind::PartitionOfUnity(pu) => Some(pu),
            ModelKind::Global(_) => None,
        }
    }

    /// Whether this is a partition-of-unity blend of local fits (false: one global spline).
    pub fn is_partition_of_unity(&self) -> bool {
        matches!(self.kind, ModelKind::PartitionOfUnity(_))
    }

    /// Number of partition-of-unity patches (0 for a global spline).
    pub fn patches(&self) -> usize {
        match &self.kind {
            ModelKind::Global(_) => 0,
            ModelKind::PartitionOfUnity(pu) => pu.patches(),
        }
    }

    /// The centres of a global spline; for a partition-of-unity model, the (merged) samples it was
    /// fitted to (each is a centre of every local fit whose patch contains it).
    pub fn centres(&self) -> &[DVec3] {
        match &self.kind {
            ModelKind::Global(g) => &g.centres,
            ModelKind::PartitionOfUnity(pu) => &pu.points,
        }
    }

    /// The RBF coefficients l_i, one per centre of a global spline; for a partition-of-unity model the
    /// local coefficients of all patches concatenated in patch order (so not aligned with [`Self::centres`]).
    pub fn coefficients(&self) -> &[f64] {
        match &self.kind {
            ModelKind::Global(g) => &g.coefficients,
            ModelKind::PartitionOfUnity(pu) => &pu.coefficients,
        }
    }

    /// The trend `(c0, c, origin)` of `c0 + c.(x - origin)`; a partition-of-unity model has only local
    /// trends and returns zeros.
    pub fn trend(&self) -> (f64, DVec3, DVec3) {
        match &self.kind {
            ModelKind::Global(g) => (g.constant, g.linear, g.origin),
            ModelKind::PartitionOfUnity(_) => (0.0, DVec3::ZERO, DVec3::ZERO),
        }
    }

    /// Smoothing weight w (mm) the model was fitted with.
    pub fn smoothing(&self) -> f64 {
        match &self.kind {
            ModelKind::Global(g) => g.smoothing,
            ModelKind::PartitionOfUnity(pu) => pu.smoothing,
        }
    }

    /// Relative accuracy of the fast evaluator (global splines; stored but unused by partition of unity,
    /// whose evaluation is exact).
    pub fn eval_accuracy(&self) -> f64 {
        match &self.kind {
            ModelKind::Global(g) => g.eval_accuracy,
            ModelKind::PartitionOfUnity(pu) => pu.eval_accuracy,
        }
    }

    /// Value at one point (global: exact direct sum over all centres).
    pub fn value(&self, p: DVec3) -> f64 {
        match &self.kind {
            ModelKind::Global(g) => g.value(p),
            ModelKind::PartitionOfUnity(pu) => pu.value(p),
        }
    }

    /// Values at many points (rayon; treecode when a global problem is large).
    pub fn values(&self, points: &[DVec3]) -> Vec<f64> {
        let mut out = vec![0.0; points.len()];
        self.evaluate(points, &mut out, None);
        out
    }

    /// Values and gradients at many points.
    pub fn values_and_gradients(&self, points: &[DVec3]) -> (Vec<f64>, Vec<DVec3>) {
        let mut values = vec![0.0; points.len()];
        let mut gradients = vec![DVec3::ZERO; points.len()];
        self.evaluate(points, &mut values, Some(&mut gradients));
        (values, gradients)
    }

    fn evaluate(&self, points: &[DVec3], values: &mut [f64], gradients: Option<&mut [DVec3]>) {
        match &self.kind {
            ModelKind::Global(g) => g.evaluate(points, values, gradients),
            ModelKind::PartitionOfUnity(pu) => pu.evaluate(points, values, gradients),
        }
    }

    /// Writes the model atomically as `.esrbf` (version 1 for global splines, 2 for partition of unity).
    pub fn save(&self, path: &Path) -> Result<()> {
        let bytes = match &self.kind {
            ModelKind::Global(g) => g.encode(),
            ModelKind::PartitionOfUnity(pu) => {
                let mut bytes =
                    Vec::with_capacity(12 + PuModel::ENCODED_HEADER_BYTES + pu.memory_bytes() + 8);
                bytes.extend_from_slice(MAGIC);
                bytes.extend_from_slice(&PU_VERSION.to_le_bytes());
                pu.encode(&mut bytes);
                let hash = fnv1a(&bytes);
                bytes.extend_from_slice(&hash.to_le_bytes());
                bytes
            }
        };
        crate::io::atomic::write_atomic(path, |w| w.write_all(&bytes))
    }

    /// Reads a `.esrbf` model; every size is checked before allocation and every number must be finite.
    pub fn load(path: &Path) -> Result<RbfModel> {
        let bad = |problem, message: String| Error::format(path, problem, message);
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        if bytes.len() < 8 || &bytes[..8] != MAGIC {
            return Err(bad(
                FormatProblem::Unsupported,
                "not an echosurf RBF model (.esrbf magic missing)".into(),
            ));
        }
        if bytes.len() < 12 {
            return Err(bad(
                FormatProblem::Truncated,
                "file ends inside the header".into(),
            ));
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        match version {
            VERSION => Ok(RbfModel {
                kind: ModelKind::Global(GlobalModel::decode(&bytes, path)?),
            }),
            PU_VERSION => {
                if bytes.len() < 12 + 8 {
                    return Err(bad(
                        FormatProblem::Truncated,
                        "file ends inside the header".into(),
                    ));
                }
                let body = bytes.len() - 8;
                let stored = u64::from_le_bytes(bytes[body..].try_into().expect("8 bytes"));
                // Sizes first (a truncated file is reported as such), then the checksum.
                let parsed = PuModel::decode(&bytes[12..body]);
                if let Err((
                    problem @ (FormatProblem::Truncated | FormatProblem::SizeMismatch),
                    m,
                )) = &parsed
                {
                    return Err(bad(*problem, m.clone()));
                }
                if fnv1a(&bytes[..body]) != stored {
                    return Err(bad(FormatProblem::Corrupt, "checksum mismatch".into()));
                }
                let model = parsed.map_err(|(problem, message)| bad(problem, message))?;
                Ok(RbfModel::from_partition_of_unity(model))
            }
            _ => Err(bad(
                FormatProblem::Unsupported,
                format!(
                    "model version {version}, this build reads versions {VERSION} and {PU_VERSION}"
                ),
            )),
        }
    }
}

impl GlobalModel {
    fn new(
        centres: Vec<DVec3>,
        coefficients: Vec<f64>,
        origin: DVec3,
        constant: f64,
        linear: DVec3,
        smoothing: f64,
        eval_accuracy: f64,
    ) -> GlobalModel {
        GlobalModel {
            centres,
            coefficients,
            origin,
            constant,
            linear,
            smoothing,
            eval_accuracy,
            fast: OnceLock::new(),
        }
    }

    fn trend_at(&self, p: DVec3) -> f64 {
        self.constant + self.linear.dot(p - self.origin)
    }

    /// Exact value at one point (direct sum over all centres).
    pub fn value(&self, p: DVec3) -> f64 {
        let mut s = 0.0;
        for (c, l) in self.centres.iter().zip(&self.coefficients) {
            s += l * (p - *c).length();
        }
        self.trend_at(p) + s
    }

    fn evaluate(&self, points: &[DVec3], values: &mut [f64], gradients: Option<&mut [DVec3]>) {
        if points.len().saturating_mul(self.centres.len()) <= DIRECT_EVALUATION_LIMIT
            || self.centres.len() < 256
        {
            self.evaluate_direct(points, values, gradients);
        } else {
            self.evaluate_fast(points, values, gradients);
        }
    }

    fn evaluate_direct(
        &self,
        points: &[DVec3],
        values: &mut [f64],
        gradients: Option<&mut [DVec3]>,
    ) {
        let xs: Vec<f64> = self.centres.iter().map(|c| c.x).collect();
        let ys: Vec<f64> = self.centres.iter().map(|c| c.y).collect();
        let zs: Vec<f64> = self.centres.iter().map(|c| c.z).collect();
        let q = &self.coefficients;
        match gradients {
            None => values
                .par_iter_mut()
                .zip(points.par_iter())
                .for_each(|(v, p)| *v = self.trend_at(*p) + sum_r(*p, &xs, &ys, &zs, q)),
            Some(g) => values
                .par_iter_mut()
                .zip(g.par_iter_mut())
                .zip(points.par_iter())
                .for_each(|((v, g), p)| {
                    let (s, grad) = sum_r_grad(*p, &xs, &ys, &zs, q);
                    *v = self.trend_at(*p) + s;
                    *g = self.linear + grad;
                }),
        }
    }

    fn fast(&self) -> &FastEvaluator {
        self.fast.get_or_init(|| {
            let treecode = Treecode::new(
                &self.centres,
                TreecodeParams::for_accuracy(self.eval_accuracy),
            );
            let charges = treecode.tree.to_tree_order(&self.coefficients);
            let proxies = treecode.upward(&charges);
            FastEvaluator {
                treecode,
                charges,
                proxies,
            }
        })
    }

    fn evaluate_fast(&self, points: &[DVec3], values: &mut [f64], gradients: Option<&mut [DVec3]>) {
        let fast = self.fast();
        let targets = Tree::build(points, 64);
        let lists = fast.treecode.interactions(&targets);
        let mut tree_values = vec![0.0; points.len()];
        let mut tree_gradients = gradients.as_ref().map(|_| vec![DVec3::ZERO; points.len()]);
        fast.treecode.evaluate(
            &targets,
            &lists,
            &fast.charges,
            &fast.proxies,
            &mut tree_values,
            tree_gradients.as_deref_mut(),
        );
        for (k, &i) in targets.order.iter().enumerate() {
            let p = points[i as usize];
            values[i as usize] = self.trend_at(p) + tree_values[k];
        }
        if let (Some(out), Some(tg)) = (gradients, tree_gradients) {
            for (k, &i) in targets.order.iter().enumerate() {
                out[i as usize] = self.linear + tg[k];
            }
        }
    }

    /// The complete version-1 file.
    fn encode(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(HEADER_BYTES + self.centres.len() * 32 + 8);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&VERSION.to_le_bytes());
        bytes.extend_from_slice(&(self.centres.len() as u64).to_le_bytes());
        for v in [
            self.smoothing,
            self.eval_accuracy,
            self.origin.x,
            self.origin.y,
            self.origin.z,
            self.constant,
            self.linear.x,
            self.linear.y,
            self.linear.z,
        ] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        for c in &self.centres {
            for v in [c.x, c.y, c.z] {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        for l in &self.coefficients {
            bytes.extend_from_slice(&l.to_le_bytes());
        }
        let hash = fnv1a(&bytes);
        bytes.extend_from_slice(&hash.to_le_bytes());
        bytes
    }

    /// Parses a complete version-1 file (magic already checked).
    fn decode(bytes: &[u8], path: &Path) -> Result<GlobalModel> {
        let bad = |problem, message: String| Error::format(path, problem, message);
        if bytes.len() < HEADER_BYTES {
            return Err(bad(
                FormatProblem::Truncated,
                "file ends inside the header".into(),
            ));
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        if version != VERSION {
            return Err(bad(
                FormatProblem::Unsupported,
                format!("model version {version}, this build reads version {VERSION}"),
            ));
        }
        let n = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
        let expected = (n as u128) * 32 + HEADER_BYTES as u128 + 8;
        if expected != bytes.len() as u128 {
            let problem = if expected > bytes.len() as u128 {
                FormatProblem::Truncated
            } else {
                FormatProblem::SizeMismatch
            };
            return Err(bad(
                problem,
                format!(
                    "header says {n} centres ({expected} bytes) but the file has {} bytes",
                    bytes.len()
                ),
            ));
        }
        let n = n as usize;
        let body = bytes.len() - 8;
        let stored = u64::from_le_bytes(bytes[body..].try_into().expect("8 bytes"));
        if fnv1a(&bytes[..body]) != stored {
            return Err(bad(FormatProblem::Corrupt, "checksum mismatch".into()));
        }
        let f = |k: usize| f64::from_le_bytes(bytes[k..k + 8].try_into().expect("8 bytes"));
        let header: Vec<f64> = (0..9).map(|k| f(20 + 8 * k)).collect();
        if header.iter().any(|v| !v.is_finite()) {
            return Err(bad(
                FormatProblem::BadValue,
                "non-finite header value".into(),
            ));
        }
        let smoothing = header[0];
        let eval_accuracy = header[1];
        if smoothing < 0.0 || !(eval_accuracy > 0.0 && eval_accuracy <= 0.1) {
            return Err(bad(
                FormatProblem::BadValue,
                format!("smoothing {smoothing} or eval accuracy {eval_accuracy} out of range"),
            ));
        }
        let base = HEADER_BYTES;
        let centres: Vec<DVec3> = (0..n)
            .map(|i| {
                let k = base + i * 24;
                DVec3::new(f(k), f(k + 8), f(k + 16))
            })
            .collect();
        let cbase = base + n * 24;
        let coefficients: Vec<f64> = (0..n).map(|i| f(cbase + i * 8)).collect();
        if centres.iter().any(|c| !c.is_finite()) || coefficients.iter().any(|v| !v.is_finite()) {
            return Err(bad(
                FormatProblem::BadValue,
                "non-finite centre or coefficient".into(),
            ));
        }
        Ok(GlobalModel::new(
            centres,
            coefficients,
            DVec3::new(header[2], header[3], header[4]),
            header[5],
            DVec3::new(header[6], header[7], header[8]),
            smoothing,
            eval_accuracy,
        ))
    }
}

fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

impl crate::surface::ScalarField for RbfModel {
    fn values(&self, points: &[DVec3], out: &mut [f64]) {
        self.evaluate(points, out, None);
    }

    fn values_and_gradients(&self, points: &[DVec3], values: &mut [f64], gradients: &mut [DVec3]) {
        self.evaluate(points, values, Some(gradients));
    }
}
