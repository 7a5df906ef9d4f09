//! An image size, width × height: one type from a command-line flag or a
//! Python keyword to the renderer, so no layer can flip a `(height, width)`
//! tuple into a `(width, height)` one.

use std::fmt;
use std::str::FromStr;

use crate::ContractError;

/// An image size in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Resolution {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

impl Resolution {
    /// `width` columns by `height` rows.
    pub const fn new(width: u32, height: u32) -> Self {
        Self { width, height }
    }
}

/// `WIDTHxHEIGHT`, as `320x240`.
impl fmt::Display for Resolution {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}x{}", self.width, self.height)
    }
}

/// Parses `WIDTHxHEIGHT` (`320x240`): what every `--resolution` flag takes.
impl FromStr for Resolution {
    type Err = ContractError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = || {
            ContractError::InvalidResolution(format!(
                "{text:?}: a resolution looks like 320x240 (width x height, in pixels)"
            ))
        };
        let (width, height) = text.split_once('x').ok_or_else(bad)?;
        Ok(Self::new(
            width.trim().parse().map_err(|_| bad())?,
            height.trim().parse().map_err(|_| bad())?,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resolution_reads_and_prints_width_first() {
        let r: Resolution = "320x240".parse().expect("parses");
        assert_eq!(r, Resolution::new(320, 240));
        assert_eq!((r.width, r.height), (320, 240));
        assert_eq!(r.to_string(), "320x240");
        for bad in ["320", "320x", "x240", "-1x5", "320x240x3", "axb", ""] {
            let e = bad.parse::<Resolution>().expect_err(bad);
            assert!(e.to_string().contains("looks like 320x240"), "{e}");
        }
    }
}
