//! Value parsers for numeric flags: every number a flag takes is finite and within a stated
//! range, checked by clap before a command runs (exit 2, naming the flag, the value and the
//! range). Integer flags use clap's ranged parsers with the bounds named here.

/// Longest duration any flag may give (a year, as in topologies), seconds: always a valid
/// wall-clock deadline.
pub const MAX_SECONDS: f64 = cloudlight::runtime::topology::MAX_SECONDS;
/// Largest image side of the reference and quality images, pixels.
pub const MAX_IMAGE_SIDE: u64 = 16_384;
/// Largest client frame side, pixels (the client shell's limit).
pub const MAX_FRAME_SIDE: u64 = cloudlight::actors::client::MAX_FRAME_PX as u64;
/// Most photons per iteration any bench may ask for (the batcher's own limit).
pub const MAX_PHOTONS: u64 = cloudlight::actors::photon_batcher::MAX_PHOTONS;
/// Most photons per batch (the batcher's).
pub const MAX_BATCH: u64 = cloudlight::actors::photon_batcher::MAX_BATCH_PHOTONS as u64;
/// Most samples per pixel of a reference image.
pub const MAX_SPP: u64 = 1_000_000;
/// Largest message of the transport bench, bytes (the probe's and the transport's limit).
pub const MAX_MESSAGE_BYTES: u64 = 64 << 20;

/// A number as a person would write it.
fn show(v: f64) -> String {
    cloudlight::runtime::stage::show_number(v)
}

/// A finite number in `[low, high]` (`(low, high]` when `open_low`), in `unit`.
fn number_in(
    low: f64,
    high: f64,
    open_low: bool,
    unit: &'static str,
) -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    move |s: &str| {
        let v: f64 = s
            .trim()
            .parse()
            .map_err(|_| format!("`{s}` is not a number"))?;
        let above = if open_low { v > low } else { v >= low };
        if v.is_finite() && above && v <= high {
            Ok(v)
        } else {
            let open = if open_low { "(" } else { "[" };
            Err(format!(
                "{} is out of range: must be a number in {open}{}, {}] {unit}",
                show(v),
                show(low),
                show(high)
            )
            .trim_end()
            .to_string())
        }
    }
}

/// A finite number in `[low, high]`.
pub fn closed(
    low: f64,
    high: f64,
    unit: &'static str,
) -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    number_in(low, high, false, unit)
}

/// A finite number in `(low, high]`.
pub fn above(
    low: f64,
    high: f64,
    unit: &'static str,
) -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    number_in(low, high, true, unit)
}

/// A duration in seconds: `(0, MAX_SECONDS]`.
pub fn seconds() -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    above(0.0, MAX_SECONDS, "seconds")
}

/// A probability in `[0, 1]`.
pub fn probability() -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    closed(0.0, 1.0, "")
}

/// A whole number in `[low, high]` (clap's ranged parser, for `u64` and smaller types).
pub fn count<T>(low: u64, high: u64) -> clap::builder::RangedU64ValueParser<T>
where
    T: TryFrom<u64> + Clone + Send + Sync + 'static,
    <T as TryFrom<u64>>::Error: std::fmt::Display + Send + Sync + 'static,
{
    clap::builder::RangedU64ValueParser::<T>::new().range(low..=high)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_outside_their_range_are_refused_with_the_range() {
        let p = seconds();
        for bad in ["nan", "inf", "-inf", "0", "-1", "1e300", "x", ""] {
            let e = p(bad).unwrap_err();
            assert!(
                e.contains("out of range") || e.contains("not a number"),
                "{bad}: {e}"
            );
        }
        assert_eq!(p("1e-300"), Ok(1e-300));
        assert!(closed(0.0, 1.0, "")("0").is_ok());
        assert!(closed(0.0, 1.0, "")("1.0000001").is_err());
    }
}
