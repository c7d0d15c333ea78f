//! The process's open-file limit (`RLIMIT_NOFILE`) and the connections it has room for.
//!
//! Every connection holds a descriptor, and so do the listeners, the runtime, metrics scrapes and
//! files read at start. At start the binary raises its soft limit to the hard one ([`raise`]);
//! the accept loop then serves at most [`Capacity::for_limit`] connections, so that it sheds
//! connections (see [`super::accept`](mod@super::accept)) before `accept` runs out of descriptors.
//!
//! On platforms without `RLIMIT_NOFILE` (not Unix) there is no limit to raise or read, and the
//! connection limit is taken as given.

/// The least headroom kept below the open-file limit: descriptors for everything but connections
/// (half of it) and for connections on their way out (the other half: answered
/// `RESOURCE_EXHAUSTED` over the limit, or shed and not closed yet).
pub const MIN_HEADROOM: u64 = 64;

/// The open-file limits before and after [`raise`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Raised {
    /// The soft limit found; `None` is unlimited.
    pub before: Option<u64>,
    /// The soft limit now in effect; `None` is unlimited.
    pub soft: Option<u64>,
    /// The hard limit; `None` is unlimited.
    pub hard: Option<u64>,
}

/// Raises the soft open-file limit to the hard limit and logs the result once. A failure is
/// logged and leaves the limit as it was: the server then sheds connections under that one.
pub fn raise() -> Option<Raised> {
    match imp::raise() {
        Ok(Some(raised)) => {
            if raised.before == raised.soft {
                tracing::info!(
                    open_files = %show(raised.soft),
                    "open-file limit already at its hard limit"
                );
            } else {
                tracing::info!(
                    from = %show(raised.before),
                    to = %show(raised.soft),
                    "raised the open-file limit to its hard limit"
                );
            }
            Some(raised)
        }
        Ok(None) => None,
        Err(e) => {
            tracing::warn!("cannot raise the open-file limit: {e}");
            None
        }
    }
}

/// The soft open-file limit in effect now; `None` when unlimited or unknown.
pub fn soft_limit() -> Option<u64> {
    imp::soft_limit()
}

fn show(limit: Option<u64>) -> String {
    limit.map_or_else(|| "unlimited".to_owned(), |n| n.to_string())
}

/// How many connections the accept loop keeps open at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Capacity {
    /// Connections admitted and served.
    pub max_connections: usize,
    /// Connections beyond `max_connections` on their way out: accepted over the limit only to be
    /// answered `RESOURCE_EXHAUSTED`, or shed and not closed yet.
    pub max_over_limit: usize,
}

impl Capacity {
    /// The capacity for a connection limit of `requested` under an open-file limit of `nofile`
    /// (`None`: unlimited or unknown, the limit is taken as given).
    ///
    /// The headroom is [`MIN_HEADROOM`] descriptors or a sixteenth of the limit, whichever is
    /// more, but never more than half of it. Connections are capped at the limit less the
    /// headroom; those on their way out may use half the headroom, and the descriptors below the
    /// cap that admitted ones leave free. The other half is for the rest of the process
    /// (listeners, the runtime, signal handling, metrics scrapes: about a dozen when idle).
    pub fn for_limit(requested: usize, nofile: Option<u64>) -> Capacity {
        let Some(limit) = nofile else {
            return Capacity {
                max_connections: requested,
                max_over_limit: requested,
            };
        };
        let headroom = MIN_HEADROOM.max(limit / 16).min(limit / 2);
        let usable = usize::try_from(limit - headroom / 2).unwrap_or(usize::MAX);
        let cap = usize::try_from(limit - headroom).unwrap_or(usize::MAX);
        let max_connections = requested.min(cap);
        Capacity {
            max_connections,
            max_over_limit: max_connections.min(usable - max_connections),
        }
    }
}

#[cfg(unix)]
mod imp {
    use rustix::process::{Resource, Rlimit, getrlimit, setrlimit};

    use super::Raised;

    pub(super) fn raise() -> std::io::Result<Option<Raised>> {
        let found = getrlimit(Resource::Nofile);
        if found.current == found.maximum {
            return Ok(Some(Raised {
                before: found.current,
                soft: found.current,
                hard: found.maximum,
            }));
        }
        setrlimit(
            Resource::Nofile,
            Rlimit {
                current: found.maximum,
                maximum: found.maximum,
            },
        )
        .map_err(|e| std::io::Error::from_raw_os_error(e.raw_os_error()))?;
        let now = getrlimit(Resource::Nofile);
        Ok(Some(Raised {
            before: found.current,
            soft: now.current,
            hard: now.maximum,
        }))
    }

    pub(super) fn soft_limit() -> Option<u64> {
        getrlimit(Resource::Nofile).current
    }
}

#[cfg(not(unix))]
mod imp {
    use super::Raised;

    pub(super) fn raise() -> std::io::Result<Option<Raised>> {
        Ok(None)
    }

    pub(super) fn soft_limit() -> Option<u64> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_keeps_headroom_below_the_open_file_limit() {
        // `ulimit -n 1024`: 64 kept, 960 served, 32 more may be answered over the limit.
        let at_1024 = Capacity::for_limit(1024, Some(1024));
        assert_eq!(
            at_1024,
            Capacity {
                max_connections: 960,
                max_over_limit: 32
            }
        );
        // A generous limit: the flag is the limit, and as many may be answered over it.
        assert_eq!(
            Capacity::for_limit(1024, Some(1 << 20)),
            Capacity {
                max_connections: 1024,
                max_over_limit: 1024
            }
        );
        // Large limits keep a sixteenth.
        assert_eq!(
            Capacity::for_limit(100_000, Some(65_536)).max_connections,
            65_536 - 4096
        );
        // Tiny limits keep half.
        let tiny = Capacity::for_limit(1024, Some(48));
        assert_eq!(tiny.max_connections, 24);
        assert_eq!(tiny.max_over_limit, 12);
        // Unknown: as given.
        assert_eq!(
            Capacity::for_limit(7, None),
            Capacity {
                max_connections: 7,
                max_over_limit: 7
            }
        );
        // Whatever the numbers, connections admitted or answered leave half the headroom free.
        for limit in [2, 16, 48, 100, 1024, 4096, 1 << 20] {
            for requested in [0, 1, 10, 1000, 1 << 30] {
                let b = Capacity::for_limit(requested, Some(limit));
                let headroom = MIN_HEADROOM.max(limit / 16).min(limit / 2);
                assert!(b.max_connections <= requested);
                assert!(
                    (b.max_connections + b.max_over_limit) as u64 <= limit - headroom / 2,
                    "{limit} {requested} {b:?}"
                );
            }
        }
    }

    #[cfg(unix)]
    #[test]
    fn raising_reaches_the_hard_limit() {
        let raised = raise().expect("getrlimit works on Unix");
        assert_eq!(raised.soft, raised.hard);
        assert_eq!(soft_limit(), raised.soft);
    }
}
