//! The bounded session table both reassemblers keep (Cyphal/CAN in [`crate::cyphal`], CCSDS
//! in [`crate::ccsds`]): `N` sessions, session `i` owning slot `i` of the caller's payload
//! storage. What the two protocols share is the life of a session, not its contents:
//! - a message in progress is abandoned (and counted) once it is older than the timeout;
//! - a new stream takes a free session, else the least recently active one that is idle or
//!   whose message has timed out; with none, the stream is refused (never a panic, never an
//!   overwrite of a live message).
//!
//! Invariant: nothing here allocates; every choice is a pure function of the sessions' times.

/// The parts of a session that its life cycle reads.
pub(crate) trait SessionTimes {
    fn in_use(&self) -> bool;
    fn in_progress(&self) -> bool;
    /// When the message in progress started (its first frame or packet), us.
    fn start_us(&self) -> u64;
    /// When the session last accepted input, us.
    fn last_activity_us(&self) -> u64;
    fn abandon(&mut self);
}

/// Abandons every message in progress older than `timeout_us` at `now_us`; returns how many.
pub(crate) fn expire<S: SessionTimes>(sessions: &mut [S], now_us: u64, timeout_us: u64) -> u64 {
    let mut abandoned = 0;
    for s in sessions.iter_mut() {
        if s.in_progress() && now_us.saturating_sub(s.start_us()) > timeout_us {
            s.abandon();
            abandoned += 1;
        }
    }
    abandoned
}

/// Which session a new stream takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Claim {
    Free(usize),
    /// Evicts a session; `abandons` when it still had a message in progress (timed out).
    Evict {
        index: usize,
        abandons: bool,
    },
}

/// A free session, else the least recently active one that is idle or whose message is
/// older than `timeout_us` (the first of equals); `None` when every session is busy.
pub(crate) fn claim<S: SessionTimes>(
    sessions: &[S],
    now_us: u64,
    timeout_us: u64,
) -> Option<Claim> {
    if let Some(free) = sessions.iter().position(|s| !s.in_use()) {
        return Some(Claim::Free(free));
    }
    let mut best: Option<usize> = None;
    for (i, s) in sessions.iter().enumerate() {
        let evictable = !s.in_progress() || now_us.saturating_sub(s.start_us()) > timeout_us;
        let older = best.is_none_or(|b| s.last_activity_us() < sessions[b].last_activity_us());
        if evictable && older {
            best = Some(i);
        }
    }
    best.map(|index| Claim::Evict {
        index,
        abandons: sessions[index].in_progress(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Clone, Copy)]
    struct S {
        in_use: bool,
        in_progress: bool,
        start_us: u64,
        last_us: u64,
    }

    impl SessionTimes for S {
        fn in_use(&self) -> bool {
            self.in_use
        }
        fn in_progress(&self) -> bool {
            self.in_progress
        }
        fn start_us(&self) -> u64 {
            self.start_us
        }
        fn last_activity_us(&self) -> u64 {
            self.last_us
        }
        fn abandon(&mut self) {
            self.in_progress = false;
        }
    }

    const BUSY: S = S {
        in_use: true,
        in_progress: true,
        start_us: 1_000,
        last_us: 1_500,
    };

    #[test]
    fn free_first_then_oldest_idle_or_timed_out_else_none() {
        let idle_recent = S {
            in_progress: false,
            last_us: 900,
            ..BUSY
        };
        let idle_old = S {
            in_progress: false,
            last_us: 100,
            ..BUSY
        };
        let free = S {
            in_use: false,
            ..BUSY
        };
        assert_eq!(
            claim(&[BUSY, free, idle_old], 2_000, 10_000),
            Some(Claim::Free(1))
        );
        assert_eq!(
            claim(&[idle_recent, BUSY, idle_old], 2_000, 10_000),
            Some(Claim::Evict {
                index: 2,
                abandons: false
            })
        );
        // Every session busy and young: refused.
        assert_eq!(claim(&[BUSY, BUSY], 2_000, 10_000), None);
        // Past the timeout a busy session is evictable, and evicting it abandons its message.
        assert_eq!(
            claim(&[BUSY, BUSY], 20_000, 10_000),
            Some(Claim::Evict {
                index: 0,
                abandons: true
            })
        );
        // Exactly at the timeout it is not yet (strictly older only).
        assert_eq!(claim(&[BUSY], 11_000, 10_000), None);
    }

    #[test]
    fn expire_abandons_only_messages_past_the_timeout() {
        let young = S {
            start_us: 5_000,
            ..BUSY
        };
        let mut sessions = [
            BUSY,
            young,
            S {
                in_progress: false,
                ..BUSY
            },
        ];
        assert_eq!(expire(&mut sessions, 12_000, 10_000), 1);
        assert!(!sessions[0].in_progress && sessions[1].in_progress);
        assert_eq!(expire(&mut sessions, 12_000, 10_000), 0);
    }
}
