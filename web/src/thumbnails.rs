//! Live thumbnails: each env's camera (what the robot sees) and its
//! overhead view, as small PNGs, pulled at a low rate whatever the number
//! of viewers. A thumbnail older than [`MAX_AGE`] is refreshed by
//! subscribing to the env's stream until one frame arrives (at most
//! [`WAIT`]) and unsubscribing: between refreshes nothing flows to this
//! service, so a sim farm stepping thousands of times a second costs it one
//! frame per env per refresh, and only while someone looks.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use offworld_runtime::codec;
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::{CameraFrameView, ImageView, PixelEncoding};
use zenoh::Session;

/// A thumbnail is served from the cache for this long.
pub const MAX_AGE: Duration = Duration::from_secs(2);
/// How long a refresh waits for a frame (an idle env publishes none).
pub const WAIT: Duration = Duration::from_millis(1500);
/// Thumbnails are at most this wide, px.
pub const MAX_WIDTH: u32 = 240;

/// Which view.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, strum::IntoStaticStr)]
#[strum(serialize_all = "snake_case")]
pub enum View {
    /// The robot's camera (its preview, `preview`: the colour image).
    Camera,
    /// The enclosure's overhead camera (`overhead/*`).
    Overhead,
}

impl View {
    /// The URL's and the page's name.
    pub fn as_str(self) -> &'static str {
        self.into()
    }

    fn key(self, env: &EnvId) -> String {
        match self {
            // The preview, not `obs`: this service never receives, nor
            // slows, every frame a stepping env sends its controller.
            View::Camera => env.key(Topic::Preview),
            View::Overhead => env.overhead_selector(),
        }
    }

    /// The colour image of one sample.
    fn image<'a>(self, payload: &'a [u8]) -> Result<ImageView<'a>, String> {
        match self {
            View::Camera => codec::decode_borrowed::<CameraFrameView>(payload)
                .map(|frame| frame.color)
                .map_err(|e| format!("an undecodable camera frame: {e}")),
            View::Overhead => codec::decode_borrowed::<ImageView>(payload)
                .map_err(|e| format!("an undecodable overhead image: {e}")),
        }
    }
}

/// A thumbnail: PNG bytes and when its frame arrived.
#[derive(Debug, Clone)]
pub struct Thumbnail {
    /// `image/png`.
    pub png: Arc<Vec<u8>>,
    /// When the frame arrived here.
    pub at: Instant,
}

/// Why there is no thumbnail.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ThumbnailError {
    /// No frame arrived within [`WAIT`] and none is cached.
    #[error("no {0} frame from this env in the last {1:.1} s (an idle env publishes none)")]
    NoFrame(&'static str, f64),
    /// A frame arrived that cannot be shown.
    #[error("{0}")]
    Unusable(String),
    /// Zenoh refused the subscription.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

type Slot = Arc<tokio::sync::Mutex<Option<Thumbnail>>>;

/// The thumbnail cache of a service.
#[derive(Clone)]
pub struct Thumbnails {
    session: Session,
    /// One slot per env and view; its lock makes viewers of the same
    /// thumbnail wait for one refresh instead of each subscribing.
    slots: Arc<Mutex<HashMap<(EnvId, View), Slot>>>,
}

impl Thumbnails {
    /// Thumbnails pulled through `session`.
    pub fn new(session: Session) -> Self {
        Self {
            session,
            slots: Arc::default(),
        }
    }

    fn slot(&self, env: &EnvId, view: View) -> Slot {
        let mut slots = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        Arc::clone(slots.entry((env.clone(), view)).or_default())
    }

    /// Forgets the thumbnails of envs not in `known` (bounds the cache by
    /// the envs discovery knows).
    pub fn retain(&self, known: impl Fn(&EnvId) -> bool) {
        let mut slots = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        slots.retain(|(env, _), _| known(env));
    }

    /// `env`'s `view`: the cached one if fresh, else a new one; a stale
    /// one when no new frame comes.
    pub async fn get(&self, env: &EnvId, view: View) -> Result<Thumbnail, ThumbnailError> {
        let slot = self.slot(env, view);
        let mut cached = slot.lock().await;
        if let Some(fresh) = cached.as_ref().filter(|t| t.at.elapsed() < MAX_AGE) {
            return Ok(fresh.clone());
        }
        match self.pull(env, view).await {
            Ok(Some(png)) => {
                let thumbnail = Thumbnail {
                    png: Arc::new(png),
                    at: Instant::now(),
                };
                *cached = Some(thumbnail.clone());
                Ok(thumbnail)
            }
            Ok(None) => cached
                .clone()
                .ok_or(ThumbnailError::NoFrame(view.as_str(), WAIT.as_secs_f64())),
            Err(e) => Err(e),
        }
    }

    /// The next frame of `env`'s `view` as a PNG thumbnail; `None` when
    /// none comes within [`WAIT`].
    async fn pull(&self, env: &EnvId, view: View) -> Result<Option<Vec<u8>>, ThumbnailError> {
        let subscriber = self
            .session
            .declare_subscriber(view.key(env))
            .with(zenoh::handlers::RingChannel::new(1))
            .await
            .map_err(|e| ThumbnailError::Zenoh(e.to_string()))?;
        let sample = tokio::time::timeout(WAIT, subscriber.recv_async()).await;
        let _ = subscriber.undeclare().await;
        let Ok(Ok(sample)) = sample else {
            return Ok(None);
        };
        let bytes = sample.payload().to_bytes();
        let image = view.image(&bytes).map_err(ThumbnailError::Unusable)?;
        thumbnail_png(&image).map(Some)
    }
}

/// `image` (rgb8 or bgr8) at most [`MAX_WIDTH`] wide (nearest pixel), as
/// a PNG.
pub fn thumbnail_png(image: &ImageView<'_>) -> Result<Vec<u8>, ThumbnailError> {
    let unusable = |why: String| ThumbnailError::Unusable(why);
    let encoding = image.validate().map_err(|e| unusable(e.to_string()))?;
    let swap = match encoding {
        PixelEncoding::Rgb8 => false,
        PixelEncoding::Bgr8 => true,
        other => return Err(unusable(format!("a {other:?} image is not a colour view"))),
    };
    let (width, height) = (image.width, image.height);
    if width == 0 || height == 0 {
        return Err(unusable("an empty image".into()));
    }
    let every = width.div_ceil(MAX_WIDTH);
    let (out_w, out_h) = (width.div_ceil(every), height.div_ceil(every));
    // `validate` checked that `data` holds `height` rows of `step` ≥ 3 ×
    // `width` bytes: every index below is inside it.
    let (step, every) = (image.step as usize, every as usize);
    let mut pixels = Vec::with_capacity(out_w as usize * out_h as usize * 3);
    for row in (0..height as usize).step_by(every) {
        let line = &image.data[row * step..(row + 1) * step];
        for column in (0..width as usize).step_by(every) {
            let p = &line[column * 3..column * 3 + 3];
            if swap {
                pixels.extend_from_slice(&[p[2], p[1], p[0]]);
            } else {
                pixels.extend_from_slice(p);
            }
        }
    }
    let mut png = Vec::new();
    let mut encoder = png::Encoder::new(&mut png, out_w, out_h);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut writer| writer.write_image_data(&pixels))
        .map_err(|e| unusable(format!("PNG encoding: {e}")))?;
    Ok(png)
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::msg::{Header, Image};

    fn image(width: u32, height: u32, encoding: &str) -> Image {
        let data = (0..width * height)
            .flat_map(|i| [(i % 251) as u8, 7, 200])
            .collect();
        Image {
            header: Header::default(),
            height,
            width,
            encoding: encoding.into(),
            is_bigendian: 0,
            step: width * 3,
            data,
        }
    }

    fn view(image: &Image) -> ImageView<'_> {
        ImageView {
            header: image.header.clone(),
            height: image.height,
            width: image.width,
            encoding: &image.encoding,
            is_bigendian: image.is_bigendian,
            step: image.step,
            data: &image.data,
        }
    }

    fn decode(png: &[u8]) -> (png::OutputInfo, Vec<u8>) {
        let mut reader = png::Decoder::new(std::io::Cursor::new(png))
            .read_info()
            .expect("a PNG");
        let mut pixels = vec![0; reader.output_buffer_size().expect("size")];
        let info = reader.next_frame(&mut pixels).expect("frame");
        pixels.truncate(info.buffer_size());
        (info, pixels)
    }

    #[test]
    fn a_camera_frame_becomes_a_small_png_of_its_pixels() {
        let big = image(640, 480, "rgb8");
        let (info, pixels) = decode(&thumbnail_png(&view(&big)).expect("png"));
        // Every third pixel: 640 / 3 → 214 columns, 480 / 3 → 160 rows.
        assert_eq!((info.width, info.height), (214, 160));
        assert_eq!(&pixels[..3], &big.data[..3]);
        // Row 1 of the thumbnail is row 3 of the frame, column 1 is column 3.
        let at = |x: usize, y: usize| &big.data[(y * 640 + x) * 3..(y * 640 + x) * 3 + 3];
        let thumb = |x: usize, y: usize| &pixels[(y * 214 + x) * 3..(y * 214 + x) * 3 + 3];
        assert_eq!(thumb(1, 1), at(3, 3));
        // A small image is kept whole; bgr8 comes out as RGB.
        let small = image(8, 6, "bgr8");
        let (info, pixels) = decode(&thumbnail_png(&view(&small)).expect("png"));
        assert_eq!((info.width, info.height), (8, 6));
        assert_eq!(&pixels[..3], &[small.data[2], small.data[1], small.data[0]]);
    }

    #[test]
    fn images_that_are_no_colour_view_are_refused() {
        let depth = Image {
            encoding: "32FC1".into(),
            step: 4 * 4,
            data: vec![0; 4 * 4 * 4],
            ..image(4, 4, "rgb8")
        };
        assert!(matches!(
            thumbnail_png(&view(&depth)),
            Err(ThumbnailError::Unusable(_))
        ));
        let short = Image {
            data: vec![0; 5],
            ..image(4, 4, "rgb8")
        };
        assert!(thumbnail_png(&view(&short)).is_err());
        let empty = image(0, 0, "rgb8");
        assert!(thumbnail_png(&view(&empty)).is_err());
    }
}
