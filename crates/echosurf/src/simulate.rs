//! Phantom simulator: tracked B-mode sweeps of known shapes with ground truth.
