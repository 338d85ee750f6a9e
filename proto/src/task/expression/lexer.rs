//! Splits a formula into tokens, each with the byte range it came from (for error messages).

use super::error::{ErrorKind, ExpressionError};

/// One token of a formula.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Tok<'s> {
    /// A finite `f32` literal.
    Number(f32),
    /// A name: an input, a constant or a function.
    Ident(&'s str),
    /// Punctuation and operators, spelled as in the source (`+`, `<=`, `&&`, `(`, ...).
    Punct(&'static str),
    /// The end of the source (always the last token).
    End,
}

/// A token and the byte range `start..end` of the source it spans.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Token<'s> {
    pub tok: Tok<'s>,
    pub start: usize,
    pub end: usize,
}

/// Operators and punctuation, two-character ones first so that `<=` is not read as `<`, `=`.
const PUNCTUATION: &[&str] = &[
    "<=", ">=", "==", "!=", "&&", "||", "+", "-", "*", "/", "^", "(", ")", "[", "]", ",", ":", "<",
    ">", "!",
];

/// The tokens of `source`, ending with [`Tok::End`].
pub(super) fn tokens(source: &str) -> Result<Vec<Token<'_>>, ExpressionError> {
    let bytes = source.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c.is_ascii_whitespace() {
            i += 1;
            continue;
        }
        let start = i;
        let tok = if c.is_ascii_digit()
            || (c == b'.' && bytes.get(i + 1).is_some_and(u8::is_ascii_digit))
        {
            i = number_end(bytes, i);
            let text = &source[start..i];
            match text.parse::<f32>() {
                Ok(v) if v.is_finite() => Tok::Number(v),
                _ => return Err(ExpressionError::new(source, start, i, ErrorKind::BadNumber)),
            }
        } else if c.is_ascii_alphabetic() || c == b'_' {
            while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                i += 1;
            }
            Tok::Ident(&source[start..i])
        } else if let Some(p) = PUNCTUATION.iter().find(|p| source[i..].starts_with(**p)) {
            i += p.len();
            Tok::Punct(p)
        } else {
            let width = source[i..].chars().next().map_or(1, char::len_utf8);
            return Err(ExpressionError::new(
                source,
                start,
                start + width,
                ErrorKind::UnexpectedCharacter,
            ));
        };
        out.push(Token { tok, start, end: i });
    }
    out.push(Token {
        tok: Tok::End,
        start: source.len(),
        end: source.len(),
    });
    Ok(out)
}

/// The end of the number starting at `i`: digits, an optional fraction, an optional exponent
/// (`1`, `1.5`, `.5`, `2.`, `1e-3`). A letter right after a number is left for the parser to
/// refuse (`2x` is not a product).
fn number_end(bytes: &[u8], mut i: usize) -> usize {
    let digits = |mut i: usize| {
        while i < bytes.len() && bytes[i].is_ascii_digit() {
            i += 1;
        }
        i
    };
    i = digits(i);
    if bytes.get(i) == Some(&b'.') {
        i = digits(i + 1);
    }
    if matches!(bytes.get(i), Some(b'e' | b'E')) {
        let mut j = i + 1;
        if matches!(bytes.get(j), Some(b'+' | b'-')) {
            j += 1;
        }
        if bytes.get(j).is_some_and(u8::is_ascii_digit) {
            i = digits(j);
        }
    }
    i
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kinds(source: &str) -> Vec<Tok<'_>> {
        tokens(source).unwrap().into_iter().map(|t| t.tok).collect()
    }

    #[test]
    fn splits_numbers_names_and_operators() {
        assert_eq!(
            kinds("s_next[3]<=1.5e-1||!a"),
            [
                Tok::Ident("s_next"),
                Tok::Punct("["),
                Tok::Number(3.0),
                Tok::Punct("]"),
                Tok::Punct("<="),
                Tok::Number(0.15),
                Tok::Punct("||"),
                Tok::Punct("!"),
                Tok::Ident("a"),
                Tok::End,
            ]
        );
        assert_eq!(
            kinds(".5 2."),
            [Tok::Number(0.5), Tok::Number(2.0), Tok::End]
        );
        // `e` without digits is not an exponent: `2e` is the number 2, then the name `e`.
        assert_eq!(kinds("2e"), [Tok::Number(2.0), Tok::Ident("e"), Tok::End]);
        let t = tokens("  a ").unwrap();
        assert_eq!((t[0].start, t[0].end), (2, 3));
        assert_eq!((t[1].start, t[1].end), (4, 4));
    }

    #[test]
    fn refuses_strange_characters_and_numbers_beyond_f32() {
        let err = tokens("a + é").unwrap_err();
        assert_eq!((err.offset, err.token.as_str()), (4, "é"));
        assert_eq!(err.kind, ErrorKind::UnexpectedCharacter);
        let err = tokens("1 + 1e39").unwrap_err();
        assert_eq!(
            (err.offset, err.token.as_str(), err.kind),
            (4, "1e39", ErrorKind::BadNumber)
        );
        let long = "9".repeat(400);
        assert_eq!(tokens(&long).unwrap_err().kind, ErrorKind::BadNumber);
    }
}
