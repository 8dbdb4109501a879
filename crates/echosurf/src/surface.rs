//! Iso-surface extraction: regularised marching tetrahedra (surface-following) and marching cubes.
