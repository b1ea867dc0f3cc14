//! `floor` (and `ceil` for `f32`) without a library call. The x86-64 baseline this crate is built
//! for has no rounding instruction (SSE4.1's `roundss`/`roundsd`), so `f32::floor` and friends are
//! calls into libm; in the per-voxel projection loops (footprints, re-projection) those calls cost
//! more than the arithmetic around them. These give exactly the library's result for every input
//! (NaN and infinities included), the sign of a zero result aside (`-0.0` comes back as `0.0`),
//! which no caller can tell apart: they compare, clamp or convert to an integer.

/// Magnitudes from which every `f64` is an integer (2^52).
const INTEGRAL_F64: f64 = 4_503_599_627_370_496.0;
/// Magnitudes from which every `f32` is an integer (2^23).
const INTEGRAL_F32: f32 = 8_388_608.0;

/// Defines `$name`, `x.floor()` for `$float`, truncating through `$int`, which holds every value
/// of smaller magnitude than `$integral` (from which on every `$float` is an integer).
macro_rules! floor_without_libm {
    ($name:ident, $float:ty, $int:ty, $integral:expr) => {
        /// `x.floor()`.
        #[inline(always)]
        pub(crate) fn $name(x: $float) -> $float {
            // NaN, infinities and large magnitudes are their own floor.
            if x.is_nan() || x.abs() >= $integral {
                return x;
            }
            let t = x as $int as $float;
            if t > x {
                t - 1.0
            } else {
                t
            }
        }
    };
}

floor_without_libm!(floor_f64, f64, i64, INTEGRAL_F64);
floor_without_libm!(floor_f32, f32, i32, INTEGRAL_F32);

/// `x.ceil()`, as `-floor(-x)` (negation is exact).
#[inline(always)]
pub(crate) fn ceil_f32(x: f32) -> f32 {
    -floor_f32(-x)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Equal to the library's result, or both NaN; a zero may differ in sign only.
    fn same64(a: f64, b: f64) -> bool {
        a == b || (a.is_nan() && b.is_nan())
    }

    fn same32(a: f32, b: f32) -> bool {
        a == b || (a.is_nan() && b.is_nan())
    }

    /// Every kind of input: integers and halves either side of zero, values next to integers,
    /// the ends of the exactly-convertible range and past it, infinities, NaN, subnormals, and a
    /// sweep of the pixel-coordinate range the callers use.
    #[test]
    fn floor_and_ceil_match_the_library() {
        let mut xs64: Vec<f64> = vec![
            0.0,
            -0.0,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            5e-324,
            -5e-324,
            INTEGRAL_F64,
            -INTEGRAL_F64,
            INTEGRAL_F64 - 0.5,
            -(INTEGRAL_F64 - 0.5),
            2f64.powi(63),
            -2f64.powi(63),
            1e300,
            -1e300,
            f64::MAX,
            f64::MIN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for i in -2000..=2000 {
            let x = f64::from(i) * 0.25;
            xs64.extend([x, x.next_up(), x.next_down(), x + 1e-9, x - 1e-9]);
        }
        for x in xs64 {
            assert!(same64(floor_f64(x), x.floor()), "floor {x:e}: {} vs {}", floor_f64(x), x.floor());
        }
        let mut xs32: Vec<f32> = vec![
            0.0,
            -0.0,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            1e-45,
            -1e-45,
            INTEGRAL_F32,
            -INTEGRAL_F32,
            INTEGRAL_F32 - 0.5,
            -(INTEGRAL_F32 - 0.5),
            2f32.powi(31),
            -2f32.powi(31),
            3e38,
            -3e38,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        for i in -2000..=2000 {
            let x = i as f32 * 0.25;
            xs32.extend([x, x.next_up(), x.next_down(), x + 1e-4, x - 1e-4]);
        }
        for x in xs32 {
            assert!(same32(floor_f32(x), x.floor()), "floor {x:e}: {} vs {}", floor_f32(x), x.floor());
            assert!(same32(ceil_f32(x), x.ceil()), "ceil {x:e}: {} vs {}", ceil_f32(x), x.ceil());
        }
    }
}
