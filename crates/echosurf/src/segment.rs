//! Band segmentation (Zhang, Rohling & Pai 2002): keep a band of pixels around the boundary in each frame.
