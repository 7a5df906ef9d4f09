//! Enums named by fixed strings in keys, messages and flags. strum derives
//! each table (`IntoStaticStr` for the name, `EnumIter` + `VariantNames` to
//! read one back); [`parse`] gives every such enum the same error text.

use strum::{IntoEnumIterator, VariantNames};

/// The variant of `E` named `text`, or an error naming `what` and every
/// accepted name: "realm must be `sim` or `real`, got `x`".
pub fn parse<E>(what: &str, text: &str) -> Result<E, String>
where
    E: IntoEnumIterator + VariantNames + Into<&'static str> + Copy,
{
    E::iter()
        .find(|variant| Into::<&'static str>::into(*variant) == text)
        .ok_or_else(|| format!("{what} must be {}, got `{text}`", one_of(E::VARIANTS)))
}

/// "`a`, `b` or `c`".
fn one_of(names: &[&str]) -> String {
    let quoted: Vec<String> = names.iter().map(|name| format!("`{name}`")).collect();
    match quoted.split_last() {
        Some((last, rest)) if !rest.is_empty() => format!("{} or {last}", rest.join(", ")),
        _ => quoted.concat(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::keys::{Component, Realm, Topic};
    use crate::msg::{LearningType, PixelEncoding};

    #[test]
    fn a_name_reads_back_as_its_variant_and_a_stranger_names_every_choice() {
        assert_eq!(parse::<Realm>("realm", "real"), Ok(Realm::Real));
        assert_eq!(
            parse::<Realm>("realm", "Real"),
            Err("realm must be `sim` or `real`, got `Real`".to_string())
        );
        assert_eq!(
            parse::<LearningType>("learning_type", "rl"),
            Err(
                "learning_type must be `end2end`, `sim2real` or `humandemos`, got `rl`".to_string()
            )
        );
        assert_eq!(
            parse::<PixelEncoding>("encoding", "16UC1"),
            Ok(PixelEncoding::Depth16UC1)
        );
    }

    #[test]
    fn every_topic_and_component_has_its_wire_name() {
        // The key chunks are the contract: these never change silently.
        let names: Vec<&str> = Topic::iter().map(Topic::as_str).collect();
        assert_eq!(
            names,
            [
                "cmd",
                "obs",
                "preview",
                "preview_cmd",
                "preview_pose",
                "preview_odom",
                "odom",
                "fault",
                "pose",
                "tracking",
                "reward",
                "status",
                "heartbeat",
                "heartbeat_echo",
                "estop",
                "estop_ack",
                "estop_state",
                "goto",
                "open",
                "spec",
                "reset",
                "step",
                "close",
                "admin",
                "leaderboard",
                "book",
                "experiments",
            ]
        );
        let components = [
            Component::Controller,
            Component::SimTwin,
            Component::RobotAgent,
            Component::TrackerAgent,
            Component::Monitor,
            Component::BaseGuard,
        ]
        .map(Component::as_str);
        assert_eq!(
            components,
            [
                "controller",
                "sim_twin",
                "robot_agent",
                "tracker_agent",
                "monitor",
                "base_guard"
            ]
        );
    }
}
