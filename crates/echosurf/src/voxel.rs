//! The voxel route users take today (PLUS / 3D Slicer): splat pixels into a grid, fill holes, then
//! marching cubes. Built in so echosurf can compare itself against it honestly on the same data.
