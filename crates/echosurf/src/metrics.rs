//! Mesh-to-mesh surface distances and topology checks for scoring against ground truth.
