//! Who may use the control socket. The socket file is mode 0660 (owner and group); on top of
//! that every connection's peer credentials (`SO_PEERCRED`) are checked: root and the
//! daemon's own user always pass, others only as members of `[service] allowed_group`
//! (primary or supplementary).

use nix::unistd::{getgrouplist, Gid, Group, Uid, User};
use std::ffi::CString;

/// The access policy of one daemon.
#[derive(Debug, Clone)]
pub struct Policy {
    pub self_uid: u32,
    /// The allowed group's name and id.
    pub group: Option<(String, u32)>,
}

impl Policy {
    /// Resolves `allowed_group` (validated at start-up).
    pub fn new(allowed_group: Option<&str>) -> anyhow::Result<Self> {
        let group = match allowed_group {
            None => None,
            Some(name) => {
                let g = Group::from_name(name)?
                    .ok_or_else(|| anyhow::anyhow!("no group named `{name}`"))?;
                Some((name.to_string(), g.gid.as_raw()))
            }
        };
        Ok(Self {
            self_uid: Uid::effective().as_raw(),
            group,
        })
    }

    /// Ok when a peer with these credentials may send requests; else why not.
    pub fn check(&self, uid: u32, gid: u32) -> Result<(), String> {
        if uid == 0 || uid == self.self_uid {
            return Ok(());
        }
        let Some((name, allowed)) = &self.group else {
            return Err(format!(
                "uid {uid} may not use this socket: no [service] allowed_group is configured (only root and the service's user may)"
            ));
        };
        if gid == *allowed || self.member(uid, gid, *allowed) {
            return Ok(());
        }
        Err(format!(
            "uid {uid} is not in the group `{name}` that may use this socket"
        ))
    }

    fn member(&self, uid: u32, gid: u32, allowed: u32) -> bool {
        let Ok(Some(user)) = User::from_uid(Uid::from_raw(uid)) else {
            return false;
        };
        let Ok(cname) = CString::new(user.name) else {
            return false;
        };
        getgrouplist(&cname, Gid::from_raw(gid))
            .map(|groups| groups.iter().any(|g| g.as_raw() == allowed))
            .unwrap_or(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn root_and_self_always_pass_others_need_the_group() {
        let p = Policy {
            self_uid: 4242,
            group: None,
        };
        assert!(p.check(0, 0).is_ok());
        assert!(p.check(4242, 7).is_ok());
        assert!(p.check(1000, 1000).is_err());
        let p = Policy {
            self_uid: 4242,
            group: Some(("lab".into(), 777)),
        };
        assert!(p.check(1000, 777).is_ok());
        // uid 65534 (nobody) has no supplementary group 777.
        let e = p.check(65534, 65534).unwrap_err();
        assert!(e.contains("`lab`"), "{e}");
    }
}
