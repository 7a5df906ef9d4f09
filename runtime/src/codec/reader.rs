//! A bounds-checked serde deserializer for little-endian XCDR1 over a byte slice.
//!
//! Encoding uses the `cdr` crate. Decoding does not, on purpose: `cdr` 0.2
//! allocates a string or byte buffer of the length prefix *before* checking it
//! against the input, so 8 hostile bytes can demand a 4 GiB allocation. This
//! reader checks every length against the bytes actually present, borrows
//! byte payloads instead of copying them, and never panics.

use serde::de::{self, DeserializeSeed, IntoDeserializer, Visitor};

use crate::error::DecodeError;

impl de::Error for DecodeError {
    fn custom<T: std::fmt::Display>(msg: T) -> Self {
        DecodeError::Invalid(msg.to_string())
    }
}

/// Reads CDR data (the bytes after the encapsulation header).
pub(crate) struct CdrReader<'de> {
    data: &'de [u8],
    pos: usize,
    /// Reading the first `data.len()` of a body this long (all of it when
    /// the payload is in one piece): a byte sequence running from inside
    /// `data` exactly to the body's end is the open tail, read as empty and
    /// left to the caller.
    body_len: Option<usize>,
    /// Where the open tail's bytes start, once read.
    tail_at: Option<usize>,
}

impl<'de> CdrReader<'de> {
    pub(crate) fn new(data: &'de [u8]) -> Self {
        Self {
            data,
            pos: 0,
            body_len: None,
            tail_at: None,
        }
    }

    /// Reads `head`, the first bytes of a body of `body_len` bytes whose
    /// last field is a byte sequence (see [`CdrReader::tail_at`]).
    pub(crate) fn with_open_tail(head: &'de [u8], body_len: usize) -> Self {
        Self {
            body_len: Some(body_len),
            ..Self::new(head)
        }
    }

    /// Offset in the body of the open tail's first byte, if one was read.
    pub(crate) fn tail_at(&self) -> Option<usize> {
        self.tail_at
    }

    /// Bytes not consumed yet.
    pub(crate) fn remaining(&self) -> &'de [u8] {
        self.data.get(self.pos..).unwrap_or_default()
    }

    fn take(&mut self, len: usize) -> Result<&'de [u8], DecodeError> {
        let end = self
            .pos
            .checked_add(len)
            .filter(|end| *end <= self.data.len())
            .ok_or(DecodeError::Truncated {
                offset: self.pos,
                needed: len.saturating_sub(self.data.len().saturating_sub(self.pos)),
            })?;
        let bytes = &self.data[self.pos..end];
        self.pos = end;
        Ok(bytes)
    }

    /// Takes a primitive of `N` bytes, aligned to `N` from the header's end.
    fn take_aligned<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let padding = (N - self.pos % N) % N;
        self.take(padding)?;
        let bytes = self.take(N)?;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        Ok(out)
    }

    fn read_u32(&mut self) -> Result<u32, DecodeError> {
        Ok(u32::from_le_bytes(self.take_aligned::<4>()?))
    }

    /// A sequence length: each element takes at least one byte, so a count
    /// larger than what is left is a lie, rejected before any allocation.
    fn read_len(&mut self) -> Result<usize, DecodeError> {
        let len = self.read_u32()? as usize;
        let left = self.data.len() - self.pos;
        if len > left {
            return Err(DecodeError::Truncated {
                offset: self.pos,
                needed: len - left,
            });
        }
        Ok(len)
    }

    fn read_str(&mut self) -> Result<&'de str, DecodeError> {
        let len = self.read_len()?;
        let bytes = self.take(len)?;
        let text = match bytes.split_last() {
            None => bytes, // tolerate a zero-length string (no terminator)
            Some((0, text)) => text,
            Some(_) => {
                return Err(DecodeError::Invalid(
                    "string is not NUL-terminated".to_owned(),
                ))
            }
        };
        std::str::from_utf8(text)
            .map_err(|e| DecodeError::Invalid(format!("string is not UTF-8: {e}")))
    }
}

macro_rules! primitive {
    ($method:ident, $visit:ident, $ty:ty, $n:literal) => {
        fn $method<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
            visitor.$visit(<$ty>::from_le_bytes(self.take_aligned::<$n>()?))
        }
    };
}

macro_rules! unsupported {
    ($($method:ident),*) => {$(
        fn $method<V: Visitor<'de>>(self, _visitor: V) -> Result<V::Value, DecodeError> {
            Err(DecodeError::Invalid(concat!("CDR cannot carry ", stringify!($method)).to_owned()))
        }
    )*};
}

impl<'de> de::Deserializer<'de> for &mut CdrReader<'de> {
    type Error = DecodeError;

    primitive!(deserialize_i8, visit_i8, i8, 1);
    primitive!(deserialize_i16, visit_i16, i16, 2);
    primitive!(deserialize_i32, visit_i32, i32, 4);
    primitive!(deserialize_i64, visit_i64, i64, 8);
    primitive!(deserialize_u8, visit_u8, u8, 1);
    primitive!(deserialize_u16, visit_u16, u16, 2);
    primitive!(deserialize_u32, visit_u32, u32, 4);
    primitive!(deserialize_u64, visit_u64, u64, 8);
    primitive!(deserialize_f32, visit_f32, f32, 4);
    primitive!(deserialize_f64, visit_f64, f64, 8);

    unsupported!(
        deserialize_any,
        deserialize_option,
        deserialize_map,
        deserialize_identifier,
        deserialize_ignored_any
    );

    fn deserialize_bool<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        match self.take_aligned::<1>()?[0] {
            0 => visitor.visit_bool(false),
            1 => visitor.visit_bool(true),
            other => Err(DecodeError::Invalid(format!("bool byte {other}"))),
        }
    }

    fn deserialize_char<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        let byte = self.take_aligned::<1>()?[0];
        if byte.is_ascii() {
            visitor.visit_char(byte as char)
        } else {
            Err(DecodeError::Invalid(format!("char byte {byte:#x}")))
        }
    }

    fn deserialize_str<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        visitor.visit_borrowed_str(self.read_str()?)
    }

    fn deserialize_string<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        self.deserialize_str(visitor)
    }

    fn deserialize_bytes<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        if let Some(body_len) = self.body_len.filter(|_| self.tail_at.is_none()) {
            let at = self.pos;
            let len = self.read_u32()? as usize;
            let start = self.pos;
            if start.checked_add(len) == Some(body_len) {
                self.tail_at = Some(start);
                self.pos = self.data.len();
                return visitor.visit_borrowed_bytes(&[]);
            }
            self.pos = at;
        }
        let len = self.read_len()?;
        visitor.visit_borrowed_bytes(self.take(len)?)
    }

    fn deserialize_byte_buf<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        self.deserialize_bytes(visitor)
    }

    fn deserialize_unit<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        visitor.visit_unit()
    }

    fn deserialize_unit_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        visitor.visit_unit()
    }

    fn deserialize_newtype_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        visitor.visit_newtype_struct(self)
    }

    fn deserialize_seq<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, DecodeError> {
        let len = self.read_len()?;
        visitor.visit_seq(Elements {
            reader: self,
            left: len,
        })
    }

    fn deserialize_tuple<V: Visitor<'de>>(
        self,
        len: usize,
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        visitor.visit_seq(Elements {
            reader: self,
            left: len,
        })
    }

    fn deserialize_tuple_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        len: usize,
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        self.deserialize_tuple(len, visitor)
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        self.deserialize_tuple(fields.len(), visitor)
    }

    fn deserialize_enum<V: Visitor<'de>>(
        self,
        _name: &'static str,
        _variants: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        visitor.visit_enum(self)
    }

    fn is_human_readable(&self) -> bool {
        false
    }
}

struct Elements<'a, 'de> {
    reader: &'a mut CdrReader<'de>,
    left: usize,
}

impl<'de> de::SeqAccess<'de> for Elements<'_, 'de> {
    type Error = DecodeError;

    fn next_element_seed<T: DeserializeSeed<'de>>(
        &mut self,
        seed: T,
    ) -> Result<Option<T::Value>, DecodeError> {
        if self.left == 0 {
            return Ok(None);
        }
        self.left -= 1;
        seed.deserialize(&mut *self.reader).map(Some)
    }

    fn size_hint(&self) -> Option<usize> {
        Some(self.left)
    }
}

impl<'de> de::EnumAccess<'de> for &mut CdrReader<'de> {
    type Error = DecodeError;
    type Variant = Self;

    fn variant_seed<V: DeserializeSeed<'de>>(
        self,
        seed: V,
    ) -> Result<(V::Value, Self), DecodeError> {
        let index = self.read_u32()?;
        let value = seed.deserialize(index.into_deserializer())?;
        Ok((value, self))
    }
}

impl<'de> de::VariantAccess<'de> for &mut CdrReader<'de> {
    type Error = DecodeError;

    fn unit_variant(self) -> Result<(), DecodeError> {
        Ok(())
    }

    fn newtype_variant_seed<T: DeserializeSeed<'de>>(
        self,
        seed: T,
    ) -> Result<T::Value, DecodeError> {
        seed.deserialize(self)
    }

    fn tuple_variant<V: Visitor<'de>>(
        self,
        len: usize,
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        de::Deserializer::deserialize_tuple(self, len, visitor)
    }

    fn struct_variant<V: Visitor<'de>>(
        self,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, DecodeError> {
        de::Deserializer::deserialize_tuple(self, fields.len(), visitor)
    }
}
