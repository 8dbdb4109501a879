//! CPU z-buffer rendering of meshes to PNG previews.
