//! How services and clients name a volume: by the id the cache assigned or by a name a user
//! gave. One type for the cache, its client, the viewer and the binary (each re-exports it).

/// A volume named by id or by name.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum VolumeKey {
    /// Cache-assigned id.
    Id(u64),
    /// User-given name.
    Name(String),
}

impl VolumeKey {
    /// The key as a user types it: `#ID` or the name.
    pub fn short(&self) -> String {
        match self {
            VolumeKey::Id(id) => format!("#{id}"),
            VolumeKey::Name(n) => n.clone(),
        }
    }
}

/// In messages: "with id 7", "named \"head\"".
impl std::fmt::Display for VolumeKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VolumeKey::Id(id) => write!(f, "with id {id}"),
            VolumeKey::Name(n) => write!(f, "named {n:?}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_key_reads_in_a_message_and_as_typed() {
        assert_eq!(VolumeKey::Id(7).to_string(), "with id 7");
        assert_eq!(VolumeKey::Name("head".into()).to_string(), "named \"head\"");
        assert_eq!(VolumeKey::Id(7).short(), "#7");
        assert_eq!(VolumeKey::Name("head".into()).short(), "head");
    }
}
