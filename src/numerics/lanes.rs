//! Four complex numbers as two arrays of four reals ([`C4`]), so that each complex operation
//! of four values is a few vector instructions, which the compiler emits from these plain
//! loops. The operations and their order are exactly those of [`num_complex::Complex64`]'s
//! operators (a product is `(a.re b.re - a.im b.im, a.re b.im + a.im b.re)`, no FMA), so a
//! kernel written with them gives the numbers of the same kernel written point by point, bit
//! for bit.

use std::ops::{Add, Mul, Neg, Sub};

use num_complex::Complex64;

/// Lanes per block.
pub const L: usize = 4;

/// Four complex numbers: the real parts, then the imaginary parts.
#[derive(Clone, Copy)]
pub struct C4 {
    pub re: [f64; L],
    pub im: [f64; L],
}

impl C4 {
    /// Zero in every lane.
    pub const ZERO: C4 = C4 {
        re: [0.0; L],
        im: [0.0; L],
    };

    /// Lane `l` is `f(l)`.
    #[inline(always)]
    pub fn of(f: impl Fn(usize) -> Complex64) -> C4 {
        let mut z = C4::ZERO;
        for l in 0..L {
            let v = f(l);
            z.re[l] = v.re;
            z.im[l] = v.im;
        }
        z
    }

    /// The lanes of a lane-major block `v`: `v[0..4]` the real parts, `v[4..8]` the imaginary
    /// ones.
    #[inline(always)]
    pub fn packed(v: &[f64]) -> C4 {
        C4 {
            re: std::array::from_fn(|l| v[l]),
            im: std::array::from_fn(|l| v[L + l]),
        }
    }

    /// Lane `l`.
    #[inline(always)]
    pub fn get(&self, l: usize) -> Complex64 {
        Complex64::new(self.re[l], self.im[l])
    }

    /// `f(re, im)` lane by lane, giving `(re, im)`.
    #[inline(always)]
    pub fn each(self, f: impl Fn(f64, f64) -> (f64, f64)) -> C4 {
        let mut z = self;
        for l in 0..L {
            (z.re[l], z.im[l]) = f(self.re[l], self.im[l]);
        }
        z
    }

    /// `f(a.re, a.im, b.re, b.im)` lane by lane of `a = self` and `b = o`.
    #[inline(always)]
    fn zip_with(self, o: C4, f: impl Fn(f64, f64, f64, f64) -> (f64, f64)) -> C4 {
        let mut z = self;
        for l in 0..L {
            (z.re[l], z.im[l]) = f(self.re[l], self.im[l], o.re[l], o.im[l]);
        }
        z
    }

    /// `self * f` of a real `f`.
    #[inline(always)]
    pub fn scale(self, f: f64) -> C4 {
        self.each(|re, im| (re * f, im * f))
    }

    /// `self + f` of a real `f`.
    #[inline(always)]
    pub fn add_re(self, f: f64) -> C4 {
        self.each(|re, im| (re + f, im))
    }

    /// `self - f` of a real `f`.
    #[inline(always)]
    pub fn sub_re(self, f: f64) -> C4 {
        self.each(|re, im| (re - f, im))
    }
}

impl Mul for C4 {
    type Output = C4;
    #[inline(always)]
    fn mul(self, o: C4) -> C4 {
        self.zip_with(o, |ar, ai, br, bi| (ar * br - ai * bi, ar * bi + ai * br))
    }
}

impl Add for C4 {
    type Output = C4;
    #[inline(always)]
    fn add(self, o: C4) -> C4 {
        self.zip_with(o, |ar, ai, br, bi| (ar + br, ai + bi))
    }
}

impl Sub for C4 {
    type Output = C4;
    #[inline(always)]
    fn sub(self, o: C4) -> C4 {
        self.zip_with(o, |ar, ai, br, bi| (ar - br, ai - bi))
    }
}

impl Neg for C4 {
    type Output = C4;
    #[inline(always)]
    fn neg(self) -> C4 {
        self.each(|re, im| (-re, -im))
    }
}
