//! The common observations (uint8 depth, with or without colour, at the
//! camera's own width) written with AVX2, 8 pixels a step: depth converted
//! in one 8-lane vector, colour spread into RGBA slots by one byte shuffle.
//! About half the time of the parent module's portable loops, which
//! spread colour in 64-bit words and store depth a byte at a time
//! (`cargo bench --bench assemble`: 84×84 RGBD 8.1–8.9 → 3.2–4.9 µs,
//! 320×240 47–61 → 24–30 µs).

use core::arch::x86_64::{__m128i, __m256, __m256i, _CMP_LT_OQ};
use pulp::{x86::V3, Simd};

use offworld_runtime::msg::ImageView;

use super::{depth_level, metres, row};

/// One uint8 observation at the source's width, from `32FC1` depth.
pub(super) struct NativeU8<'i, 'a> {
    /// Colour, 3 bytes a pixel (`rgb8`, or `bgr8` swapped afterwards by
    /// the caller); `None`: depth only.
    pub color: Option<&'i ImageView<'a>>,
    /// Little-endian metres.
    pub depth: &'i ImageView<'a>,
    /// Pixels a row.
    pub width: usize,
    /// Output row `y` samples source row `source_row(y)`.
    pub source_row: &'i dyn Fn(usize) -> usize,
    /// uint8 levels per metre.
    pub scale: f32,
}

/// Writes `image` into `data` (4 or 1 bytes a pixel, rows of
/// `image.width`); false, touching nothing, on a CPU without AVX2.
pub(super) fn write_native_u8(image: &NativeU8<'_, '_>, data: &mut [u8]) -> bool {
    let Some(simd) = V3::try_new() else {
        return false;
    };
    // The trait's entry point (V3's own `vectorize` takes a closure).
    Simd::vectorize(simd, Fill { simd, image, data });
    true
}

struct Fill<'n, 'i, 'a, 'd> {
    simd: V3,
    image: &'n NativeU8<'i, 'a>,
    data: &'d mut [u8],
}

/// Per 128-bit half: three colour bytes of each of 4 pixels, a zero byte
/// after each (where the depth level goes). The upper half starts 8 bytes
/// into the 24 colour bytes of 8 pixels, so pixel 4 is at its byte 4.
const RGB_TO_RGBX: [u8; 32] = {
    const Z: u8 = 0x80; // pshufb writes 0
    [
        0, 1, 2, Z, 3, 4, 5, Z, 6, 7, 8, Z, 9, 10, 11, Z, //
        4, 5, 6, Z, 7, 8, 9, Z, 10, 11, 12, Z, 13, 14, 15, Z,
    ]
};

/// Per 128-bit half: the low byte of each 32-bit lane, into its first 4
/// bytes.
const LOW_BYTES: [u8; 32] = {
    const Z: u8 = 0x80;
    [
        0, 4, 8, 12, Z, Z, Z, Z, Z, Z, Z, Z, Z, Z, Z, Z, //
        0, 4, 8, 12, Z, Z, Z, Z, Z, Z, Z, Z, Z, Z, Z, Z,
    ]
};

impl pulp::WithSimd for Fill<'_, '_, '_, '_> {
    type Output = ();

    // Inlined into pulp's AVX2 entry point, so the intrinsics are too.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let Self { simd, image, data } = self;
        let (avx, avx2) = (simd.avx, simd.avx2);
        let w = image.width;
        let scale = avx._mm256_set1_ps(image.scale);
        let (zero, top) = (avx._mm256_set1_ps(0.0), avx._mm256_set1_ps(255.0));
        let infinity = avx._mm256_set1_ps(f32::INFINITY);
        let magnitude = avx._mm256_castsi256_ps(avx._mm256_set1_epi32(i32::MAX));
        // The level of 8 depths: non-finite is 0 m, then the saturating
        // cast `(m · scale) as u8` (truncation) of the parent's `depth_level`.
        let levels = |metres: [u8; 32]| -> __m256i {
            let m: __m256 = pulp::cast(metres);
            let finite = avx._mm256_cmp_ps::<_CMP_LT_OQ>(avx._mm256_and_ps(m, magnitude), infinity);
            let m = avx._mm256_and_ps(m, finite);
            // m · scale is never NaN here (finite times finite); zero as the
            // second operand of max would win if it were.
            let v = avx._mm256_min_ps(avx._mm256_max_ps(avx._mm256_mul_ps(m, scale), zero), top);
            avx._mm256_cvttps_epi32(v)
        };
        let rgb_to_rgbx: __m256i = pulp::cast(RGB_TO_RGBX);
        let low_bytes: __m256i = pulp::cast(LOW_BYTES);
        // The first 32 bits of each 128-bit half (4 levels each) side by side.
        let halves_first_words = avx._mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
        let pixel = if image.color.is_some() { 4 } else { 1 };
        for (y, out) in data.chunks_exact_mut(w * pixel).enumerate() {
            let sy = (image.source_row)(y);
            let depth = row(image.depth, sy, w * 4);
            let (depth_blocks, depth_rest) = depth.as_chunks::<32>();
            match image.color {
                Some(color) => {
                    let rgb = row(color, sy, w * 3);
                    let (out_blocks, out_rest) = out.as_chunks_mut::<32>();
                    let (rgb_blocks, rgb_rest) = rgb.as_chunks::<24>();
                    for ((o, c), d) in out_blocks.iter_mut().zip(rgb_blocks).zip(depth_blocks) {
                        let lo: [u8; 16] = std::array::from_fn(|i| c[i]);
                        let hi: [u8; 16] = std::array::from_fn(|i| c[8 + i]);
                        let rgb = avx._mm256_setr_m128i(
                            pulp::cast::<_, __m128i>(lo),
                            pulp::cast::<_, __m128i>(hi),
                        );
                        let rgbx = avx2._mm256_shuffle_epi8(rgb, rgb_to_rgbx);
                        let depth = avx2._mm256_slli_epi32::<24>(levels(*d));
                        *o = pulp::cast(avx2._mm256_or_si256(rgbx, depth));
                    }
                    let rest = out_rest.chunks_exact_mut(4).zip(rgb_rest.chunks_exact(3));
                    for ((o, c), d) in rest.zip(depth_rest.chunks_exact(4)) {
                        let level = depth_level(metres(d), image.scale);
                        o.copy_from_slice(&[c[0], c[1], c[2], level]);
                    }
                }
                None => {
                    let (out_blocks, out_rest) = out.as_chunks_mut::<8>();
                    for (o, d) in out_blocks.iter_mut().zip(depth_blocks) {
                        let bytes = avx2._mm256_shuffle_epi8(levels(*d), low_bytes);
                        let packed = avx2._mm256_permutevar8x32_epi32(bytes, halves_first_words);
                        let [eight, _, _, _]: [[u8; 8]; 4] = pulp::cast(packed);
                        *o = eight;
                    }
                    for (o, d) in out_rest.iter_mut().zip(depth_rest.chunks_exact(4)) {
                        *o = depth_level(metres(d), image.scale);
                    }
                }
            }
        }
    }
}
