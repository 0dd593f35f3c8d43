//! Camera frame ids within a step.
//!
//! A GenICam camera numbers its frames. GigE Vision 1.x block ids are 16 bits and skip 0:
//! after 65535 comes 1. USB3 Vision and GigE Vision 2 extended ids are 64 bits and do not
//! wrap. A step's frame `k` is the `k`-th id after the step's first.

/// The largest 16-bit block id; the next is 1.
pub const WRAP16: u64 = 65_535;

/// How many frames after `base` the camera made frame `id` (0 for `base` itself), or `None`
/// if `id` comes before `base` (a frame of an earlier step). Ids up to [`WRAP16`] are taken
/// as wrapping 16-bit block ids; an id more than half the id space ahead counts as before.
pub fn frames_after(base: u64, id: u64) -> Option<u64> {
    if base <= WRAP16 && id <= WRAP16 && base != 0 && id != 0 {
        let d = if id >= base { id - base } else { id + WRAP16 - base };
        (d < WRAP16 / 2).then_some(d)
    } else {
        id.checked_sub(base)
    }
}

/// The id `n` frames after `id` (16-bit block ids wrap past 65535 to 1).
pub fn advance(id: u64, n: u64) -> u64 {
    if id != 0 && id <= WRAP16 {
        (id - 1 + n) % WRAP16 + 1
    } else {
        id + n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sixteen_bit_ids_wrap_past_65535_to_1() {
        assert_eq!(frames_after(65_401, 65_401), Some(0));
        assert_eq!(frames_after(65_401, 65_535), Some(134));
        assert_eq!(frames_after(65_401, 1), Some(135));
        assert_eq!(frames_after(65_535, 3), Some(3));
        assert_eq!(advance(65_534, 1), 65_535);
        assert_eq!(advance(65_535, 1), 1);
        assert_eq!(advance(65_401, 200), 66);
        for (base, n) in [(1, 0), (65_000, 1000), (30_000, 32_000), (65_535, 1)] {
            assert_eq!(frames_after(base, advance(base, n)), Some(n), "{base} + {n}");
        }
        // Behind the base: a frame of an earlier step.
        assert_eq!(frames_after(500, 499), None);
        assert_eq!(frames_after(3, 65_530), None);
    }

    #[test]
    fn extended_ids_do_not_wrap() {
        assert_eq!(frames_after(70_000, 70_010), Some(10));
        assert_eq!(frames_after(70_000, 69_999), None);
        assert_eq!(advance(70_000, 5), 70_005);
    }
}
