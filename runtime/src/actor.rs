//! The ractor shell around a [`Stage`]: one actor per stage instance, plus the run
//! supervisor that turns actor failures and panics into named [`RunEvent`]s.
//!
//! The actor's mailbox carries only `Ready(input)` notifications (at most one per input
//! edge at a time, see [`crate::edge`]) and `Tick`s, so it stays bounded.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use ractor::{Actor, ActorId, ActorProcessingErr, ActorRef, SupervisionEvent};
use tokio::sync::mpsc::UnboundedSender;

use crate::edge::Edge;
use crate::stage::{Input, NextTick, Stage, StageCtx};

/// Messages of a stage actor.
#[derive(Debug)]
pub(crate) enum StageMsg {
    /// Input edge `i` has a message queued.
    Ready(usize),
    /// Time for the stage's `on_tick`.
    Tick,
}

pub(crate) struct InputEdge {
    pub(crate) edge: Arc<Edge>,
    pub(crate) port: Arc<str>,
    pub(crate) from: Arc<str>,
}

pub(crate) struct StageArgs {
    pub(crate) stage: Box<dyn Stage>,
    pub(crate) ctx: StageCtx,
    pub(crate) inputs: Vec<InputEdge>,
}

pub(crate) struct StageState {
    stage: Box<dyn Stage>,
    ctx: StageCtx,
    inputs: Vec<InputEdge>,
    /// Whether this stage still counts as a ticker in the run control.
    ticker: bool,
}

impl StageState {
    fn retire_ticker(&mut self) {
        if self.ticker {
            self.ticker = false;
            self.ctx.control.done_ticker();
        }
    }
}

pub(crate) struct StageActor;

fn failure(ctx: &StageCtx, what: &str, e: anyhow::Error) -> ActorProcessingErr {
    format!(
        "stage `{}` ({}) failed in {what}: {e:#}",
        ctx.info.name, ctx.info.kind
    )
    .into()
}

impl Actor for StageActor {
    type Msg = StageMsg;
    type State = StageState;
    type Arguments = StageArgs;

    async fn pre_start(
        &self,
        myself: ActorRef<StageMsg>,
        args: StageArgs,
    ) -> Result<StageState, ActorProcessingErr> {
        let StageArgs {
            mut stage,
            mut ctx,
            inputs,
        } = args;
        stage
            .on_start(&mut ctx)
            .await
            .map_err(|e| failure(&ctx, "on_start", e))?;
        for (i, input) in inputs.iter().enumerate() {
            let me = myself.clone();
            // A failed cast means the actor is gone; the lifecycle reports that separately.
            input.edge.set_waker(move || {
                let _ = me.cast(StageMsg::Ready(i));
            });
        }
        ctx.control.add_ticker();
        Ok(StageState {
            stage,
            ctx,
            inputs,
            ticker: true,
        })
    }

    async fn handle(
        &self,
        myself: ActorRef<StageMsg>,
        msg: StageMsg,
        state: &mut StageState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            StageMsg::Ready(i) => {
                let (edge, port, from) = {
                    let input = &state.inputs[i];
                    (input.edge.clone(), input.port.clone(), input.from.clone())
                };
                if let Some(delivery) = edge.pop() {
                    let control = state.ctx.control.clone();
                    // Held across the handler so that `pending` cannot reach zero before
                    // the stage's own sends, even if it drops the input early.
                    control.add_pending();
                    state.ctx.blocked = Duration::ZERO;
                    let start = Instant::now();
                    let input = Input::new(port, from, delivery);
                    let result = state.stage.on_input(&mut state.ctx, input).await;
                    let blocked = state.ctx.blocked;
                    state.ctx.metrics.record(
                        false,
                        start.elapsed().saturating_sub(blocked),
                        blocked,
                    );
                    control.done_pending();
                    result.map_err(|e| failure(&state.ctx, "on_input", e))?;
                }
                edge.rearm();
            }
            StageMsg::Tick => {
                if !state.ctx.control.enter_tick() {
                    state.retire_ticker();
                    return Ok(());
                }
                state.ctx.blocked = Duration::ZERO;
                let start = Instant::now();
                let result = state.stage.on_tick(&mut state.ctx).await;
                let blocked = state.ctx.blocked;
                state
                    .ctx
                    .metrics
                    .record(true, start.elapsed().saturating_sub(blocked), blocked);
                state.ctx.control.leave_tick();
                match result {
                    Ok(NextTick::Now) => {
                        let _ = myself.cast(StageMsg::Tick);
                    }
                    Ok(NextTick::After(d)) => {
                        myself.send_after(d, || StageMsg::Tick);
                    }
                    Ok(NextTick::Never) => state.retire_ticker(),
                    Err(e) => {
                        state.retire_ticker();
                        return Err(failure(&state.ctx, "on_tick", e));
                    }
                }
            }
        }
        Ok(())
    }

    async fn post_stop(
        &self,
        _myself: ActorRef<StageMsg>,
        state: &mut StageState,
    ) -> Result<(), ActorProcessingErr> {
        state.retire_ticker();
        state
            .stage
            .on_stop(&mut state.ctx)
            .await
            .map_err(|e| failure(&state.ctx, "on_stop", e))
    }
}

/// What the supervisor tells the lifecycle.
#[derive(Debug, Clone)]
pub enum RunEvent {
    /// A stage returned an error or panicked; it has stopped.
    Failed {
        /// Instance name.
        stage: Arc<str>,
        /// The error, with its causes.
        error: String,
    },
    /// A stage actor terminated (normally or killed).
    Terminated {
        /// Instance name.
        stage: Arc<str>,
    },
}

pub(crate) type Names = Arc<Mutex<HashMap<ActorId, Arc<str>>>>;

pub(crate) struct RunSupervisor;

pub(crate) struct SupervisorState {
    pub(crate) names: Names,
    pub(crate) events: UnboundedSender<RunEvent>,
}

impl RunSupervisor {
    fn name_of(state: &SupervisorState, id: ActorId) -> Arc<str> {
        crate::toolkit::lock(&state.names)
            .get(&id)
            .cloned()
            .unwrap_or_else(|| Arc::from(format!("actor {id}")))
    }
}

impl Actor for RunSupervisor {
    type Msg = ();
    type State = SupervisorState;
    type Arguments = SupervisorState;

    async fn pre_start(
        &self,
        _myself: ActorRef<()>,
        args: SupervisorState,
    ) -> Result<SupervisorState, ActorProcessingErr> {
        Ok(args)
    }

    async fn handle_supervisor_evt(
        &self,
        _myself: ActorRef<()>,
        event: SupervisionEvent,
        state: &mut SupervisorState,
    ) -> Result<(), ActorProcessingErr> {
        // The receiver is gone only after the run ended; nothing is left to tell.
        match event {
            SupervisionEvent::ActorFailed(cell, error) => {
                let stage = Self::name_of(state, cell.get_id());
                let _ = state.events.send(RunEvent::Failed {
                    stage: stage.clone(),
                    error: error.to_string(),
                });
                let _ = state.events.send(RunEvent::Terminated { stage });
            }
            SupervisionEvent::ActorTerminated(cell, _, _) => {
                let stage = Self::name_of(state, cell.get_id());
                let _ = state.events.send(RunEvent::Terminated { stage });
            }
            _ => {}
        }
        Ok(())
    }
}
