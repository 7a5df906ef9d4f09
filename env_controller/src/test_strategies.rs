//! Proptest strategies for strings (the `std`-only regex strategies are
//! left out; see the dev-dependency in Cargo.toml).

use proptest::prelude::*;

/// Strings of `len` characters drawn from `alphabet`.
pub fn text(
    alphabet: &'static [char],
    len: std::ops::RangeInclusive<usize>,
) -> impl Strategy<Value = String> {
    proptest::collection::vec(proptest::sample::select(alphabet), len)
        .prop_map(|chars| chars.into_iter().collect())
}

/// Characters where validators go wrong: controls, spaces, punctuation,
/// bidi overrides, non-ASCII letters, wildcards and key separators.
const TRICKY: &[char] = &[
    '\0', '\n', '\t', '\u{7}', '\u{1b}', ' ', '\u{a0}', '\u{202e}', '\u{200b}', '/', '*', '$', '@',
    '#', ';', '"', '\'', '\\', '-', '_', '.', 'é', '実', '😀', 'a', 'Z', '0',
];

/// Any string, up to 300 characters, biased towards [`TRICKY`] ones.
pub fn any_text() -> impl Strategy<Value = String> {
    let one = prop_oneof![any::<char>(), proptest::sample::select(TRICKY)];
    proptest::collection::vec(one, 0..=300).prop_map(|chars| chars.into_iter().collect())
}

/// ASCII letters and digits.
pub const ALNUM: &[char] = &[
    'A', 'B', 'C', 'X', 'Y', 'Z', 'a', 'b', 'c', 'x', 'y', 'z', '0', '1', '5', '9',
];
