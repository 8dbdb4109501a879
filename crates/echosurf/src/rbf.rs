//! The biharmonic RBF engine: fit `s(x) = c0 + c.x + sum_i l_i |x - x_i|` to all samples, evaluate it fast.
