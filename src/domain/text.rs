//! Caps on the free text a client may send: serials, references, names, designations. Every
//! string that is stored or echoed has one, checked before anything is stored, so that no field can
//! bloat the database, a list page or an error message (issue 48). The caps are stated in the
//! OpenAPI document as `maxLength`, in characters.

/// A part's serial number (plants' serials are a heat and a pipe number, tens of characters).
pub const SERIAL_CHARS: usize = 128;
/// A connection designation (`BC 4-1/2`, or a custom thread's name).
pub const CONNECTION_CHARS: usize = 64;
/// A view's id in a bundle.
pub const VIEW_ID_CHARS: usize = 64;
/// A frame's path in a bundle (as long as a tar header's path).
pub const FRAME_PATH_CHARS: usize = 255;
/// A client's correlation id.
pub const CLIENT_REFERENCE_CHARS: usize = 200;
/// A CMM's instrument name.
pub const INSTRUMENT_CHARS: usize = 200;
/// An RFC 3339 time, with room for a long fraction and an offset.
pub const TIMESTAMP_CHARS: usize = 64;
/// An API key's name.
pub const KEY_NAME_CHARS: usize = 100;
/// A learned model's name.
pub const MODEL_NAME_CHARS: usize = 64;
/// A station's name, and a master's serial (a part's serial).
pub const STATION_NAME_CHARS: usize = 64;

/// How a capped text failed: too long, or holding a control character.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TextError {
    #[error("has {chars} characters; at most {max}")]
    TooLong { chars: usize, max: usize },
    #[error("is empty")]
    Empty,
    #[error("holds a control character (U+{0:04X}); only printable text is taken")]
    Control(u32),
}

/// Checks `value` against a cap of `max_chars` characters, non-empty and without control
/// characters. Counting stops past the cap, so a huge value costs no more than a short one.
pub fn check(value: &str, max_chars: usize) -> Result<(), TextError> {
    if value.is_empty() {
        return Err(TextError::Empty);
    }
    let counted = value.chars().take(max_chars + 1).count();
    if counted > max_chars {
        return Err(TextError::TooLong { chars: value.chars().count(), max: max_chars });
    }
    if let Some(c) = value.chars().find(|c| c.is_control()) {
        return Err(TextError::Control(c as u32));
    }
    Ok(())
}

/// A station's name: what bundles and submissions name it by and its URL segment, so 1–64 of
/// `A–Z a–z 0–9 . _ -`, starting with a letter or digit.
pub fn check_station_name(value: &str) -> Result<(), String> {
    check(value, STATION_NAME_CHARS).map_err(|e| e.to_string())?;
    let ok = value.chars().next().is_some_and(|c| c.is_ascii_alphanumeric())
        && value.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "{:?} is not a station name: 1–64 of A–Z a–z 0–9 . _ -, starting with a letter or digit",
            preview(value)
        ))
    }
}

/// A value as an error message may quote it: its first 40 characters, an ellipsis after.
pub fn preview(value: &str) -> String {
    const SHOWN: usize = 40;
    let mut shown: String = value.chars().take(SHOWN).collect();
    if value.chars().nth(SHOWN).is_some() {
        shown.push('…');
    }
    format!("{shown:?}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caps_count_characters_and_refuse_control_characters() {
        assert_eq!(check("BC 4-1/2", CONNECTION_CHARS), Ok(()));
        assert_eq!(check(&"é".repeat(128), SERIAL_CHARS), Ok(()));
        assert_eq!(check(&"é".repeat(129), SERIAL_CHARS), Err(TextError::TooLong { chars: 129, max: 128 }));
        assert_eq!(check("", SERIAL_CHARS), Err(TextError::Empty));
        assert_eq!(check("a\u{0}b", SERIAL_CHARS), Err(TextError::Control(0)));
        assert_eq!(check("a\nb", SERIAL_CHARS), Err(TextError::Control(10)));
    }

    #[test]
    fn a_preview_quotes_at_most_forty_characters() {
        assert_eq!(preview("short"), "\"short\"");
        let long = "x".repeat(65_536);
        let p = preview(&long);
        assert_eq!(p.chars().count(), 40 + 1 + 2);
        assert!(p.ends_with("…\""));
    }
}
