//! `arbitrary` support for the heapless fields (heapless does not implement it). Used by the
//! property tests and the fuzzers; compiled only with the `arbitrary` feature.

use arbitrary::{Arbitrary, Result, Unstructured};

/// An arbitrary `heapless::Vec` of at most `N` elements.
pub fn vec<'a, T: Arbitrary<'a>, const N: usize>(u: &mut Unstructured<'a>) -> Result<heapless::Vec<T, N>> {
    let len = u.int_in_range(0..=N)?;
    let mut v = heapless::Vec::new();
    for _ in 0..len {
        // Cannot overflow: at most N pushes.
        let _ = v.push(T::arbitrary(u)?);
    }
    Ok(v)
}

/// An arbitrary `heapless::String` of at most `N` bytes, cut at a character boundary.
pub fn string<const N: usize>(u: &mut Unstructured<'_>) -> Result<heapless::String<N>> {
    let s: &str = u.arbitrary()?;
    let mut out = heapless::String::new();
    for c in s.chars() {
        if out.push(c).is_err() {
            break;
        }
    }
    Ok(out)
}
