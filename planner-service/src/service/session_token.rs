//! Agent session tokens: what tells an agent's own observations from anyone else's using its
//! name. Zenoh lets any peer publish on any key, so the name in a key proves nothing; the token
//! handed back by attach, which only the attaching process sees, does.

use rand::TryRng;
use rand::rngs::SysRng;

/// Why no token could be drawn.
#[derive(Debug, thiserror::Error)]
#[error("the OS random number generator failed: {0}")]
pub struct TokenError(#[from] rand::rngs::SysError);

/// A fresh session token: 64 bits from the OS random number generator (unguessable by another
/// client), never [`proto::NO_SESSION`] (0) — what an observation without a token carries.
pub(crate) fn new_token() -> Result<u64, TokenError> {
    loop {
        let token = SysRng.try_next_u64()?;
        if token != proto::NO_SESSION {
            return Ok(token);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_are_never_zero_and_do_not_repeat() {
        let tokens: std::collections::HashSet<u64> =
            (0..1000).map(|_| new_token().unwrap()).collect();
        assert_eq!(
            tokens.len(),
            1000,
            "1000 draws of 64 random bits repeated one"
        );
        assert!(!tokens.contains(&proto::NO_SESSION));
    }
}
