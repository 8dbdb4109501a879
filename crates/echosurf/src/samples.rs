//! Samples: kept pixels mapped to 3D points with their intensity, and their thinning.
