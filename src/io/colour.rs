//! Colourised previews of float maps (turbo colormap).

use super::OwnedImage;
use muir::input::PixelFormat;

/// Colour of pixels without a valid value (non-finite, or non-positive for uncertainty).
pub const INVALID_COLOUR: [u8; 3] = [0, 0, 0];

/// Lower and upper percentiles of the automatic colour range.
const AUTO_RANGE: (f32, f32) = (0.01, 0.99);

/// Start of the turbo domain used: the fit's first 3 % is nearly black, too close to
/// [`INVALID_COLOUR`].
const TURBO_START: f32 = 0.03;

/// The turbo colormap (Mikhailov 2019, polynomial fit by R. Du) at `t` in `[0, 1]` (clamped):
/// blue at 0 through green to dark red at 1 (the near-black first 3 % of turbo is skipped). NaN
/// maps to 0.
pub fn turbo(t: f32) -> [u8; 3] {
    const R4: [f64; 4] = [0.135_721_38, 4.615_392_6, -42.660_322_58, 132.131_082_34];
    const G4: [f64; 4] = [0.091_402_61, 2.194_188_39, 4.842_966_58, -14.185_033_33];
    const B4: [f64; 4] = [0.106_673_3, 12.641_946_08, -60.582_048_36, 110.362_767_71];
    const R2: [f64; 2] = [-152.942_393_96, 59.286_379_43];
    const G2: [f64; 2] = [4.277_298_57, 2.829_566_04];
    const B2: [f64; 2] = [-89.903_109_12, 27.348_249_73];
    let x = f64::from(TURBO_START + (1.0 - TURBO_START) * if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) });
    let v4 = [1.0, x, x * x, x * x * x];
    let v2 = [x * x * x * x, x * x * x * x * x];
    let ch = |c4: &[f64; 4], c2: &[f64; 2]| {
        let v = c4.iter().zip(&v4).map(|(a, b)| a * b).sum::<f64>() + c2[0] * v2[0] + c2[1] * v2[1];
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    };
    [ch(&R4, &R2), ch(&G4, &G2), ch(&B4, &B2)]
}

/// The `p`-quantile (`p` in `[0, 1]`) of the finite values, linearly interpolated; `None` if
/// there are none.
pub fn percentile(values: &[f32], p: f32) -> Option<f32> {
    let mut v: Vec<f32> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_unstable_by(f32::total_cmp);
    Some(quantile_sorted(&v, p))
}

fn quantile_sorted(sorted: &[f32], p: f32) -> f32 {
    let pos = p.clamp(0.0, 1.0) * (sorted.len() - 1) as f32;
    let i = pos.floor() as usize;
    let j = (i + 1).min(sorted.len() - 1);
    let f = pos - i as f32;
    sorted[i] + (sorted[j] - sorted[i]) * f
}

/// Robust range of the finite values (1st..99th percentile); `(0, 1)` if there are none.
fn auto_range(values: impl Iterator<Item = f32>) -> (f32, f32) {
    let mut v: Vec<f32> = values.filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return (0.0, 1.0);
    }
    v.sort_unstable_by(f32::total_cmp);
    (quantile_sorted(&v, AUTO_RANGE.0), quantile_sorted(&v, AUTO_RANGE.1))
}

/// Paints `mapped(i)` (already transformed, `None` = invalid) over `[lo, hi]`.
fn paint(width: usize, height: usize, (lo, hi): (f32, f32), mapped: impl Fn(usize) -> Option<f32>) -> OwnedImage {
    let span = hi - lo;
    let mut data = Vec::with_capacity(width * height * 3);
    for i in 0..width * height {
        let rgb = match mapped(i) {
            Some(v) if span.is_finite() && span != 0.0 => turbo((v - lo) / span),
            Some(_) => turbo(0.5),
            None => INVALID_COLOUR,
        };
        data.extend_from_slice(&rgb);
    }
    OwnedImage { width, height, format: PixelFormat::Rgb8, data }
}

/// RGB preview of a disparity map (`width * height` values, row-major): turbo from `range.0`
/// (dark blue, far) to `range.1` (dark red, near); non-finite values (and any pixel past the end
/// of `values`) in [`INVALID_COLOUR`]. Without a range, the 1st..99th percentile of the finite
/// values is used.
pub fn colourise_disparity(values: &[f32], width: usize, height: usize, range: Option<(f32, f32)>) -> OwnedImage {
    let valid = |i: usize| values.get(i).copied().filter(|v| v.is_finite());
    let range = range.unwrap_or_else(|| auto_range((0..width * height).filter_map(valid)));
    paint(width, height, range, valid)
}

/// RGB preview of a predicted-error map in pixels, on a log scale: turbo from `range.0` px (dark
/// blue, confident) to `range.1` px (dark red); non-finite or non-positive values in
/// [`INVALID_COLOUR`]. Without a range, the 1st..99th percentile of the log errors is used.
pub fn colourise_uncertainty(err_px: &[f32], width: usize, height: usize, range: Option<(f32, f32)>) -> OwnedImage {
    let log = |i: usize| err_px.get(i).copied().filter(|v| v.is_finite() && *v > 0.0).map(f32::ln);
    let range = match range {
        Some((lo, hi)) => (lo.max(f32::MIN_POSITIVE).ln(), hi.max(f32::MIN_POSITIVE).ln()),
        None => auto_range((0..width * height).filter_map(log)),
    };
    paint(width, height, range, log)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turbo_ends_and_middle() {
        let [r0, g0, b0] = turbo(0.0);
        assert!(b0 > r0 && b0 > g0, "low end is blue-ish: {:?}", turbo(0.0));
        let [r1, g1, b1] = turbo(1.0);
        assert!(r1 > g1 && r1 > b1, "high end is red-ish: {:?}", turbo(1.0));
        let [rm, gm, bm] = turbo(0.5);
        assert!(gm > rm.max(bm) / 2 && gm > 200, "middle is green-ish: {:?}", turbo(0.5));
        assert_eq!(turbo(-3.0), turbo(0.0));
        assert_eq!(turbo(7.0), turbo(1.0));
        assert_eq!(turbo(f32::NAN), turbo(0.0));
        assert!(turbo(0.0).iter().map(|&c| c as u32).sum::<u32>() > 150, "low end far from black");
    }

    #[test]
    fn percentiles() {
        let v = [4.0, f32::NAN, 1.0, 3.0, f32::INFINITY, 2.0];
        assert_eq!(percentile(&v, 0.0), Some(1.0));
        assert_eq!(percentile(&v, 1.0), Some(4.0));
        assert_eq!(percentile(&v, 0.5), Some(2.5));
        assert_eq!(percentile(&[f32::NAN], 0.5), None);
    }

    #[test]
    fn disparity_preview() {
        let mut v: Vec<f32> = (0..200).map(|i| i as f32).collect();
        v[3] = f32::INFINITY;
        v[4] = f32::NAN;
        let im = colourise_disparity(&v, 20, 10, None);
        assert_eq!((im.width, im.height, im.format, im.data.len()), (20, 10, PixelFormat::Rgb8, 600));
        assert_eq!(&im.data[9..15], &[0; 6]);
        assert_eq!(&im.data[0..3], &turbo(0.0));
        assert_eq!(&im.data[597..600], &turbo(1.0));
        // Fixed range; a short slice leaves the rest invalid; a constant map is drawn mid-scale.
        let im = colourise_disparity(&[0.0, 10.0, 5.0], 2, 2, Some((0.0, 10.0)));
        assert_eq!(im.data, [turbo(0.0), turbo(1.0), turbo(0.5), INVALID_COLOUR].concat());
        let im = colourise_disparity(&[2.0; 4], 2, 2, None);
        assert_eq!(&im.data[0..3], &turbo(0.5));
    }

    #[test]
    fn uncertainty_preview_is_logarithmic() {
        let im = colourise_uncertainty(&[0.5, 2.0, 8.0, 0.0], 4, 1, Some((0.5, 8.0)));
        assert_eq!(im.data, [turbo(0.0), turbo(0.5), turbo(1.0), INVALID_COLOUR].concat());
        let im = colourise_uncertainty(&[1.0, 10.0, 100.0, -1.0], 2, 2, None);
        assert_eq!(&im.data[9..12], &INVALID_COLOUR);
        assert_eq!(&im.data[0..3], &turbo(0.0));
    }
}
