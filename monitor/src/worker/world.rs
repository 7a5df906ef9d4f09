//! Each env's world: asked of its controller (`spec`) off the worker's
//! thread, retried once, drawn with the scene and the blueprint.

use super::*;

impl Worker {
    pub(super) fn send_blueprint(&self) {
        let blueprint = layout::blueprint(&self.order);
        if let Err(e) = blueprint.send(&self.rec, rerun::blueprint::BlueprintActivation::default())
        {
            tracing::debug!("monitor could not send its blueprint: {e}");
        }
    }

    /// Starts finding out which world `env` uses: the configured one at
    /// once, else the controller's `spec` on a helper thread (the worker
    /// never waits on the network).
    pub(super) fn resolve_world(&mut self, env: &EnvId) {
        if let Some(name) = self.config.world.clone() {
            let (world, source) = match WorldSpec::builtin(&name) {
                Ok(w) => (w, WorldSource::Configured),
                Err(e) => match fallback_world() {
                    Some(w) => (w, WorldSource::Fallback(e.to_string())),
                    None => return,
                },
            };
            self.apply_world(env, world, source, SystemTime::now());
            return;
        }
        let Some(session) = self.session.clone() else {
            // A replay: the recording says.
            return;
        };
        if let Some(view) = self.envs.get_mut(env) {
            if view.resolving {
                return;
            }
            view.resolving = true;
        }
        let (shared, env, timeout) = (self.shared.clone(), env.clone(), self.config.spec_timeout);
        let spawned = std::thread::Builder::new()
            .name("monitor-spec".into())
            .spawn(move || {
                let (world, source) = query_world(&session, &env, timeout);
                shared.queue.push(
                    Lane::Control,
                    Event::World {
                        env,
                        world: world.map(Box::new),
                        source,
                    },
                );
            });
        if let Err(e) = spawned {
            tracing::warn!("monitor could not start a spec query: {e}");
        }
    }

    /// A fallback world gets one more chance once the env's controller shows
    /// signs of life.
    pub(super) fn maybe_retry_world(&mut self, env: &EnvId) {
        let Some(view) = self.envs.get_mut(env) else {
            return;
        };
        if view.retried || view.resolving || self.config.world.is_some() {
            return;
        }
        if matches!(view.world_source, Some(WorldSource::Fallback(_))) {
            view.retried = true;
            self.resolve_world(env);
        }
    }

    /// Draws `world` for `env` (if it is not drawn already); its event is
    /// logged at `wall`.
    pub fn apply_world(
        &mut self,
        env: &EnvId,
        world: WorldSpec,
        source: WorldSource,
        wall: SystemTime,
    ) {
        let view = self.view(env);
        view.resolving = false;
        let previous = view.world.take();
        let changed = previous.as_ref().is_none_or(|p| p.name != world.name);
        let camera_res = view.camera_res;
        view.world_source = Some(source.clone());
        let result = (|| -> Result<(), rerun::RecordingStreamError> {
            if changed {
                self.rec.reset_time();
                scene::log_world(&self.rec, env, &world, previous.as_ref())?;
                scene::log_robot_bodies(&self.rec, env, &world.robot)?;
                if let Some((w, h)) = camera_res {
                    scene::log_camera(&self.rec, env, &world.camera, w, h)?;
                }
            }
            Ok(())
        })();
        if let Err(e) = result {
            self.count(&self.shared.counters.log_errors);
            tracing::debug!("monitor could not log the world: {e}");
        }
        if changed {
            let text = match &source {
                WorldSource::Configured => format!("world: {} (configured)", world.name),
                WorldSource::Spec => format!("world: {} (from the env's spec)", world.name),
                WorldSource::Recording => format!("world: {} (recorded)", world.name),
                WorldSource::Fallback(why) => {
                    format!("world: {} (default; {why})", world.name)
                }
            };
            let stamp = Self::stamp(None, None, wall);
            let level = rerun::TextLogLevel::DEBUG;
            self.row(env, paths::EVENTS, stamp, Row::Text(text, level));
        }
        let view = self.view(env);
        if let Some((w, h)) = camera_res {
            view.pinhole_res = Some((w, h));
        }
        view.world = Some(world);
    }

    // ---- samples ---------------------------------------------------------
}

/// Asks the env's controller which world it serves; falls back to
/// [`FALLBACK_WORLD`] when nobody answers or the world is unknown.
pub(super) fn query_world(
    session: &Session,
    env: &EnvId,
    timeout: Duration,
) -> (Option<WorldSpec>, WorldSource) {
    let fallback = |why: String| (fallback_world(), WorldSource::Fallback(why));
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => return fallback(format!("no runtime for the spec query: {e}")),
    };
    let reply = runtime.block_on(offworld_client::spec(session, env, timeout));
    match reply {
        Ok(spec) => match WorldSpec::builtin(&spec.world) {
            Ok(world) => (Some(world), WorldSource::Spec),
            Err(e) => fallback(format!("the env's world: {e}")),
        },
        Err(e) => fallback(format!("no spec: {}", e.message)),
    }
}
