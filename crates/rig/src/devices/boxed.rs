//! The device traits as trait objects, so that the drivers' table can hand any driver of a
//! kind to that kind's one device task. One boxed future per call: nothing next to a device
//! exchange.

use std::future::Future;
use std::pin::Pin;

use dioptra_core::{
    DeviceError, DeviceWarning, Diopters, GazeSample, GazeSource, LensState, LightEvent,
    Photodiode, PlaneSchedule, PlaneSequencer, PowerRange, SequencerEvent, Timestamp,
    VarifocalLens,
};

pub(crate) type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// [`VarifocalLens`] in a form that can be boxed.
pub trait DynLens: Send {
    fn power_range(&self) -> PowerRange;
    fn set_power(&mut self, power: Diopters) -> BoxFuture<'_, Result<Timestamp, DeviceError>>;
    fn state(&mut self) -> BoxFuture<'_, Result<LensState, DeviceError>>;
    fn take_warnings(&mut self) -> Vec<DeviceWarning>;
}

impl<T: VarifocalLens> DynLens for T {
    fn power_range(&self) -> PowerRange {
        VarifocalLens::power_range(self)
    }
    fn set_power(&mut self, power: Diopters) -> BoxFuture<'_, Result<Timestamp, DeviceError>> {
        Box::pin(VarifocalLens::set_power(self, power))
    }
    fn state(&mut self) -> BoxFuture<'_, Result<LensState, DeviceError>> {
        Box::pin(VarifocalLens::state(self))
    }
    fn take_warnings(&mut self) -> Vec<DeviceWarning> {
        VarifocalLens::take_warnings(self)
    }
}

/// Any lens driver.
pub struct BoxLens(pub Box<dyn DynLens>);

impl VarifocalLens for BoxLens {
    fn power_range(&self) -> PowerRange {
        self.0.power_range()
    }
    fn set_power(
        &mut self,
        power: Diopters,
    ) -> impl Future<Output = Result<Timestamp, DeviceError>> + Send {
        self.0.set_power(power)
    }
    fn state(&mut self) -> impl Future<Output = Result<LensState, DeviceError>> + Send {
        self.0.state()
    }
    fn take_warnings(&mut self) -> Vec<DeviceWarning> {
        self.0.take_warnings()
    }
}

/// [`GazeSource`] in a form that can be boxed.
pub trait DynGaze: Send {
    fn rate_hz(&self) -> f32;
    fn next_sample(&mut self) -> BoxFuture<'_, Result<GazeSample, DeviceError>>;
}

impl<T: GazeSource> DynGaze for T {
    fn rate_hz(&self) -> f32 {
        GazeSource::rate_hz(self)
    }
    fn next_sample(&mut self) -> BoxFuture<'_, Result<GazeSample, DeviceError>> {
        Box::pin(GazeSource::next_sample(self))
    }
}

/// Any eye-tracker driver.
pub struct BoxGaze(pub Box<dyn DynGaze>);

impl GazeSource for BoxGaze {
    fn rate_hz(&self) -> f32 {
        self.0.rate_hz()
    }
    fn next_sample(&mut self) -> impl Future<Output = Result<GazeSample, DeviceError>> + Send {
        self.0.next_sample()
    }
}

/// [`PlaneSequencer`] in a form that can be boxed.
pub trait DynSequencer: Send {
    fn program<'a>(
        &'a mut self,
        schedule: &'a PlaneSchedule,
    ) -> BoxFuture<'a, Result<(), DeviceError>>;
    fn start(&mut self) -> BoxFuture<'_, Result<(), DeviceError>>;
    fn stop(&mut self) -> BoxFuture<'_, Result<(), DeviceError>>;
    fn next_event(&mut self) -> BoxFuture<'_, Result<SequencerEvent, DeviceError>>;
}

impl<T: PlaneSequencer> DynSequencer for T {
    fn program<'a>(
        &'a mut self,
        schedule: &'a PlaneSchedule,
    ) -> BoxFuture<'a, Result<(), DeviceError>> {
        Box::pin(PlaneSequencer::program(self, schedule))
    }
    fn start(&mut self) -> BoxFuture<'_, Result<(), DeviceError>> {
        Box::pin(PlaneSequencer::start(self))
    }
    fn stop(&mut self) -> BoxFuture<'_, Result<(), DeviceError>> {
        Box::pin(PlaneSequencer::stop(self))
    }
    fn next_event(&mut self) -> BoxFuture<'_, Result<SequencerEvent, DeviceError>> {
        Box::pin(PlaneSequencer::next_event(self))
    }
}

/// Any sync-hardware driver.
pub struct BoxSequencer(pub Box<dyn DynSequencer>);

impl PlaneSequencer for BoxSequencer {
    fn program(
        &mut self,
        schedule: &PlaneSchedule,
    ) -> impl Future<Output = Result<(), DeviceError>> + Send {
        // A copy, so the future borrows only `self`.
        let schedule = schedule.clone();
        async move { self.0.program(&schedule).await }
    }
    fn start(&mut self) -> impl Future<Output = Result<(), DeviceError>> + Send {
        self.0.start()
    }
    fn stop(&mut self) -> impl Future<Output = Result<(), DeviceError>> + Send {
        self.0.stop()
    }
    fn next_event(&mut self) -> impl Future<Output = Result<SequencerEvent, DeviceError>> + Send {
        self.0.next_event()
    }
}

/// [`Photodiode`] in a form that can be boxed.
pub trait DynPhotodiode: Send {
    fn next_light(&mut self) -> BoxFuture<'_, Result<LightEvent, DeviceError>>;
}

impl<T: Photodiode> DynPhotodiode for T {
    fn next_light(&mut self) -> BoxFuture<'_, Result<LightEvent, DeviceError>> {
        Box::pin(Photodiode::next_light(self))
    }
}

/// Any photodiode driver.
pub struct BoxPhotodiode(pub Box<dyn DynPhotodiode>);

impl Photodiode for BoxPhotodiode {
    fn next_light(&mut self) -> impl Future<Output = Result<LightEvent, DeviceError>> + Send {
        self.0.next_light()
    }
}
