//! Tokens: what tells an agent's own messages from anyone else's using its name. Zenoh lets
//! any peer publish on any key, so the name in a key proves nothing; a token that only one
//! process has seen does. Planners draw the session token an accepted attach hands back;
//! an agent draws the token its first attach presents ([`crate::AttachRequest::session`]), so
//! that asking again for an answer it never received proves it is the same agent.

use rand::TryRng;
use rand::rngs::SysRng;

use crate::messages::NO_SESSION;

/// Why no token could be drawn.
#[derive(Debug, thiserror::Error)]
#[error("the OS random number generator failed: {0}")]
pub struct TokenError(#[from] rand::rngs::SysError);

/// A fresh token: 64 bits from the OS random number generator (unguessable by another
/// client), never [`NO_SESSION`] (0), what an observation without a token carries.
pub fn draw_token() -> Result<u64, TokenError> {
    loop {
        let token = SysRng.try_next_u64()?;
        if token != NO_SESSION {
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
            (0..1000).map(|_| draw_token().unwrap()).collect();
        assert_eq!(
            tokens.len(),
            1000,
            "1000 draws of 64 random bits repeated one"
        );
        assert!(!tokens.contains(&NO_SESSION));
    }
}
