//! Why a formula was refused, and where.

use std::fmt;

/// A formula that cannot be used: what is wrong ([`ErrorKind`]), the offending text and its byte
/// offset in the source. `Display` renders it as `s[7]: index 7 out of range for s (obs_dim 4)
/// at 12`, followed by the surrounding source with a caret line under the offending text.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{token}: {kind} at {offset}\n{excerpt}")]
pub struct ExpressionError {
    /// Byte offset of the offending text in the source.
    pub offset: usize,
    /// The offending text (shortened when long), or `end of input`.
    pub token: String,
    pub kind: ErrorKind,
    /// Two lines: the source around the offending text, and carets under it.
    excerpt: String,
}

/// What is wrong with a formula.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ErrorKind {
    #[error("the formula is {len} bytes long, more than the {max} allowed")]
    TooLong { len: usize, max: usize },
    #[error("nested more than {max} levels deep")]
    TooDeep { max: usize },
    #[error("more than {max} operations once vectors are expanded")]
    TooLarge { max: usize },
    #[error("unexpected character")]
    UnexpectedCharacter,
    #[error("not a number that fits in f32")]
    BadNumber,
    #[error("expected {0}")]
    Expected(&'static str),
    #[error("unknown name (known: s, a, s_next, pi, e)")]
    UnknownName,
    #[error("unknown function (known: {})", super::parser::FUNCTIONS.join(", "))]
    UnknownFunction,
    #[error("{function} takes {expected} arguments, got {got}")]
    Arity {
        function: &'static str,
        expected: &'static str,
        got: usize,
    },
    #[error("an index must be a non-negative whole number")]
    BadIndex,
    #[error("index {index} out of range for {of}")]
    IndexOutOfRange { index: usize, of: String },
    #[error("slice {start}:{end} out of range or empty for {of}")]
    BadSlice {
        start: usize,
        end: usize,
        of: String,
    },
    #[error("only a vector can be indexed")]
    NotAVector,
    #[error("a vector of length {0} where a scalar is needed")]
    NotAScalar(usize),
    #[error("vectors of lengths {0} and {1} do not match")]
    LengthMismatch(usize, usize),
    #[error("comparisons do not chain: join them with && or ||")]
    ChainedComparison,
    #[error("a reduction of an empty vector (a dimension is 0)")]
    EmptyVector,
}

/// Longest offending text quoted in an error.
const MAX_TOKEN_CHARS: usize = 40;
/// Characters of context shown on each side of the offending text.
const CONTEXT_CHARS: usize = 30;

impl ExpressionError {
    /// The error `kind` about the text `start..end` of `source` (byte offsets on character
    /// boundaries).
    pub(super) fn new(source: &str, start: usize, end: usize, kind: ErrorKind) -> Self {
        let text = &source[start..end];
        let token = if text.is_empty() {
            "end of input".to_string()
        } else if text.chars().count() > MAX_TOKEN_CHARS {
            let head: String = text.chars().take(MAX_TOKEN_CHARS).collect();
            format!("{head}…")
        } else {
            text.to_string()
        };
        Self {
            offset: start,
            token: printable(&token),
            kind,
            excerpt: excerpt(source, start, end),
        }
    }

    /// The error about a formula longer than the bound: quoting it would be pointless.
    pub(super) fn too_long(len: usize, max: usize) -> Self {
        Self {
            offset: max,
            token: "the formula".to_string(),
            kind: ErrorKind::TooLong { len, max },
            excerpt: String::new(),
        }
    }
}

/// `text` on one line: whitespace and control characters become spaces.
fn printable(text: &str) -> String {
    text.chars()
        .map(|c| {
            if c.is_control() || c.is_whitespace() {
                ' '
            } else {
                c
            }
        })
        .collect()
}

/// The source around `start..end` on one line, and a line with carets under `start..end`.
fn excerpt(source: &str, start: usize, end: usize) -> String {
    let before: Vec<char> = source[..start].chars().rev().take(CONTEXT_CHARS).collect();
    let marked: Vec<char> = source[start..end].chars().take(MAX_TOKEN_CHARS).collect();
    let after: String = source[start..]
        .chars()
        .skip(marked.len())
        .take(CONTEXT_CHARS)
        .collect();
    let lead = if before.len() == CONTEXT_CHARS && before.len() < source[..start].chars().count() {
        "…"
    } else {
        ""
    };
    let before: String = before.into_iter().rev().collect();
    let marked: String = marked.into_iter().collect();
    let mut out = String::new();
    use fmt::Write;
    let _ = write!(
        out,
        "  {lead}{}",
        printable(&(before.clone() + &marked + &after))
    );
    let _ = write!(
        out,
        "\n  {}{}",
        " ".repeat(lead.chars().count() + before.chars().count()),
        "^".repeat(marked.chars().count().max(1))
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_the_offending_text_with_a_caret_line() {
        let source = "exp(-s[0]^2) + s[7]";
        let err = ExpressionError::new(
            source,
            15,
            19,
            ErrorKind::IndexOutOfRange {
                index: 7,
                of: "s (obs_dim 4)".into(),
            },
        );
        assert_eq!(
            err.to_string(),
            "s[7]: index 7 out of range for s (obs_dim 4) at 15\n  \
             exp(-s[0]^2) + s[7]\n                 ^^^^"
        );
        let end = ExpressionError::new("(a", 2, 2, ErrorKind::Expected("`)`"));
        assert_eq!(
            end.to_string(),
            "end of input: expected `)` at 2\n  (a\n    ^"
        );
    }

    #[test]
    fn long_sources_are_cut_around_the_error() {
        let source = format!("{}\n+ x{}", "a[0] + ".repeat(100), " + a[0]".repeat(100));
        let at = source.find('x').unwrap();
        let err = ExpressionError::new(&source, at, at + 1, ErrorKind::UnknownName);
        let text = err.to_string();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 3, "{text}");
        assert!(lines[1].chars().count() < 2 * CONTEXT_CHARS + 10, "{text}");
        let caret = lines[2].chars().position(|c| c == '^').unwrap();
        assert_eq!(lines[1].chars().nth(caret), Some('x'), "{text}");
        let long = "b".repeat(100);
        assert!(
            ExpressionError::new(&long, 0, 100, ErrorKind::UnknownName)
                .token
                .ends_with('…')
        );
    }
}
