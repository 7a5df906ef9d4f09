//! Network namespaces for a deployment test: the router in a namespace of
//! its own, reachable from the host (where trainers run) over one veth pair
//! and from a site namespace (controller, twins, agents) over another. The
//! router namespace does not forward IP, so the host and the site can only
//! meet through the router's Zenoh session. Needs `ip` and CAP_NET_ADMIN.

use std::process::Command;

/// Two namespaces and two veth pairs, removed on drop.
pub struct Namespaces {
    /// The router's namespace.
    pub router: String,
    /// The site's namespace.
    pub site: String,
    /// The router's address on the host link (trainers connect here).
    pub router_host_ip: String,
    /// The router's address on the site link (site components connect here).
    pub router_site_ip: String,
    /// The site namespace's own address.
    pub site_ip: String,
    /// The host's address on the host link.
    pub host_ip: String,
    host_link: String,
}

fn ip(args: &[&str]) -> anyhow::Result<()> {
    let out = Command::new("ip").args(args).output()?;
    anyhow::ensure!(
        out.status.success(),
        "ip {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr).trim()
    );
    Ok(())
}

impl Namespaces {
    /// Creates the namespaces and links; an error says why (no `ip`, no
    /// privilege), and leaves nothing behind.
    pub fn create() -> anyhow::Result<Self> {
        // Unique per process: interface names stay within 15 characters,
        // and concurrent test processes get disjoint subnets.
        let id = std::process::id() % 100_000;
        let net = 16 + id % 200;
        let ns = Self {
            router: format!("ow-router-{id}"),
            site: format!("ow-site-{id}"),
            router_host_ip: format!("10.{net}.1.2"),
            router_site_ip: format!("10.{net}.2.1"),
            site_ip: format!("10.{net}.2.2"),
            host_ip: format!("10.{net}.1.1"),
            host_link: format!("owh-{id}"),
        };
        ns.build(id).inspect_err(|_| ns.remove())?;
        Ok(ns)
    }

    /// Where a router site runs in these namespaces
    /// ([`offworld_deploy::site::RouterSite::start_namespaced`]).
    pub fn placement(&self) -> offworld_deploy::site::Namespaced {
        offworld_deploy::site::Namespaced {
            router: self.router.clone(),
            site: self.site.clone(),
            router_host_ip: self.router_host_ip.clone(),
            router_site_ip: self.router_site_ip.clone(),
        }
    }

    /// Whether namespace `ns` has a route to `addr` (`ip route get`).
    pub fn routes(ns: &str, addr: &str) -> bool {
        ip(&["-n", ns, "route", "get", addr]).is_ok()
    }

    fn build(&self, id: u32) -> anyhow::Result<()> {
        let (r, s) = (self.router.as_str(), self.site.as_str());
        let (rh, rs, sv) = (
            format!("owrh-{id}"),
            format!("owrs-{id}"),
            format!("owsv-{id}"),
        );
        ip(&["netns", "add", r])?;
        ip(&["netns", "add", s])?;
        ip(&[
            "link",
            "add",
            &self.host_link,
            "type",
            "veth",
            "peer",
            "name",
            &rh,
        ])?;
        ip(&["link", "set", &rh, "netns", r])?;
        ip(&["link", "add", &sv, "type", "veth", "peer", "name", &rs])?;
        ip(&["link", "set", &rs, "netns", r])?;
        ip(&["link", "set", &sv, "netns", s])?;
        let host_ip = format!("{}/24", self.host_ip);
        ip(&["addr", "add", &host_ip, "dev", &self.host_link])?;
        ip(&["link", "set", &self.host_link, "up"])?;
        for (ns, dev, addr) in [
            (r, rh.as_str(), format!("{}/24", self.router_host_ip)),
            (r, rs.as_str(), format!("{}/24", self.router_site_ip)),
            (s, sv.as_str(), format!("{}/24", self.site_ip)),
        ] {
            ip(&["-n", ns, "addr", "add", &addr, "dev", dev])?;
            ip(&["-n", ns, "link", "set", dev, "up"])?;
        }
        for ns in [r, s] {
            ip(&["-n", ns, "link", "set", "lo", "up"])?;
        }
        Ok(())
    }

    fn remove(&self) {
        // Deleting a namespace deletes its veth ends and so their peers.
        let _ = ip(&["netns", "del", &self.router]);
        let _ = ip(&["netns", "del", &self.site]);
        let _ = ip(&["link", "del", &self.host_link]);
    }
}

impl Drop for Namespaces {
    fn drop(&mut self) {
        self.remove();
    }
}

/// One namespace for the robot computer, reachable from the host (the
/// site: controller, trainers) over one veth pair. What runs inside listens
/// on the namespace's own loopback for its neighbours, which the host
/// cannot reach: the host meets the robot only through the addresses it is
/// given, so a test can put a [`crate::link::ImpairedLink`] in that path.
pub struct RobotNamespace {
    /// The namespace's name (`ip netns exec <name> …`).
    pub name: String,
    /// The robot's address on the link.
    pub robot_ip: String,
    /// The host's address on the link.
    pub host_ip: String,
    host_link: String,
}

impl RobotNamespace {
    /// Creates the namespace and its link; an error says why (no `ip`, no
    /// privilege), and leaves nothing behind.
    pub fn create() -> anyhow::Result<Self> {
        let id = std::process::id() % 100_000;
        // Disjoint from [`Namespaces`]' 10.16–215 subnets.
        let net = 216 + id % 39;
        let sub = (id / 39) % 250;
        let ns = Self {
            name: format!("ow-robot-{id}"),
            robot_ip: format!("10.{net}.{sub}.2"),
            host_ip: format!("10.{net}.{sub}.1"),
            host_link: format!("owb-{id}"),
        };
        ns.build(id).inspect_err(|_| ns.remove())?;
        Ok(ns)
    }

    fn build(&self, id: u32) -> anyhow::Result<()> {
        let inside = format!("owbr-{id}");
        ip(&["netns", "add", &self.name])?;
        ip(&[
            "link",
            "add",
            &self.host_link,
            "type",
            "veth",
            "peer",
            "name",
            &inside,
        ])?;
        ip(&["link", "set", &inside, "netns", &self.name])?;
        let host_ip = format!("{}/24", self.host_ip);
        ip(&["addr", "add", &host_ip, "dev", &self.host_link])?;
        ip(&["link", "set", &self.host_link, "up"])?;
        let robot_ip = format!("{}/24", self.robot_ip);
        ip(&["-n", &self.name, "addr", "add", &robot_ip, "dev", &inside])?;
        ip(&["-n", &self.name, "link", "set", &inside, "up"])?;
        ip(&["-n", &self.name, "link", "set", "lo", "up"])?;
        Ok(())
    }

    fn remove(&self) {
        let _ = ip(&["netns", "del", &self.name]);
        let _ = ip(&["link", "del", &self.host_link]);
    }
}

impl Drop for RobotNamespace {
    fn drop(&mut self) {
        self.remove();
    }
}
