//! The device traits as trait objects, so that the drivers' table can hand any driver of a
//! kind to that kind's one device task, and to the device commands (`dioptra lens|gaze|sync`).
//! One boxed future per call: nothing next to a device exchange. Beside its kind's trait each
//! boxed driver says who it is ([`About`]), and a sequencer whether it can take a new link
//! ([`Resume`]): what the device commands print and do without knowing the driver.

use std::future::Future;
use std::pin::Pin;

use dioptra_core::{
    DeviceError, Diopters, GazeSample, GazeSource, LensState, LightEvent, Photodiode,
    PlaneSchedule, PlaneSequencer, PowerRange, SequencerEvent, Timestamp, VarifocalLens,
};
use dioptra_transport::{AnyByteLink, AnyHidLink};

/// What a driver connects over: a real device's link or a simulator's (the drivers' table in
/// `open.rs` makes it).
pub enum Link {
    Byte(AnyByteLink),
    Hid(AnyHidLink),
    /// The address of a network service.
    Net(String),
}

impl Link {
    fn kind(&self) -> &'static str {
        match self {
            Link::Byte(_) => "a byte link",
            Link::Hid(_) => "a HID link",
            Link::Net(_) => "a network address",
        }
    }
    /// The byte link, or an error naming `what` (the driver) and the link it was given.
    pub fn byte(self, what: &str) -> Result<AnyByteLink, DeviceError> {
        match self {
            Link::Byte(l) => Ok(l),
            other => Err(DeviceError::Invalid(format!(
                "the {what} driver talks over a byte link, and was given {}",
                other.kind()
            ))),
        }
    }
    /// The HID link, or an error naming `what` and the link it was given.
    pub fn hid(self, what: &str) -> Result<AnyHidLink, DeviceError> {
        match self {
            Link::Hid(l) => Ok(l),
            other => Err(DeviceError::Invalid(format!(
                "the {what} driver talks over HID, and was given {}",
                other.kind()
            ))),
        }
    }
    /// The network address, or an error naming `what` and the link it was given.
    pub fn net(self, what: &str) -> Result<String, DeviceError> {
        match self {
            Link::Net(a) => Ok(a),
            other => Err(DeviceError::Invalid(format!(
                "the {what} driver talks over the network, and was given {}",
                other.kind()
            ))),
        }
    }
}

pub(crate) type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// What a device says about itself: labelled facts in the device's words ("serial", "ABC123"),
/// in the order a person reads them.
pub type Facts = Vec<(&'static str, String)>;

/// Who a connected device is, for the device commands' `info` and `status` and for
/// provenance (a calibration table names the lens it was measured on). Each driver of the
/// drivers' table implements it (`devices/about.rs`).
pub trait About: Send {
    /// One line naming the device: its kind, serial number and firmware where it said them.
    fn identity(&self) -> String;
    /// Its identity, limits and state as facts, read from the device where they need a read.
    fn about(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>>;
    /// Its condition now (temperature, status bits) where it reports one; nothing by default.
    fn condition(&mut self) -> BoxFuture<'_, Result<Facts, DeviceError>> {
        Box::pin(async { Ok(Facts::new()) })
    }
}

/// A sequencer that can take a new link after an unplug and restore its session (its
/// schedule, running or not). By default it cannot: the command ends and says so.
pub trait Resume: Send {
    /// Whether [`Resume::resume`] can restore a session on a new link.
    fn resumes(&self) -> bool {
        false
    }
    fn resume(&mut self, link: Link) -> BoxFuture<'_, Result<(), DeviceError>> {
        drop(link);
        Box::pin(async {
            Err(DeviceError::Invalid(
                "this device cannot resume its session on a new link".into(),
            ))
        })
    }
}

/// [`VarifocalLens`] and [`About`] in a form that can be boxed.
pub trait DynLens: About {
    fn power_range(&self) -> PowerRange;
    fn set_power(&mut self, power: Diopters) -> BoxFuture<'_, Result<Timestamp, DeviceError>>;
    fn state(&mut self) -> BoxFuture<'_, Result<LensState, DeviceError>>;
}

impl<T: VarifocalLens + About> DynLens for T {
    fn power_range(&self) -> PowerRange {
        VarifocalLens::power_range(self)
    }
    fn set_power(&mut self, power: Diopters) -> BoxFuture<'_, Result<Timestamp, DeviceError>> {
        Box::pin(VarifocalLens::set_power(self, power))
    }
    fn state(&mut self) -> BoxFuture<'_, Result<LensState, DeviceError>> {
        Box::pin(VarifocalLens::state(self))
    }
}

/// Any lens driver.
pub struct BoxLens(pub Box<dyn DynLens>);

impl BoxLens {
    pub fn identity(&self) -> String {
        self.0.identity()
    }
    pub async fn about(&mut self) -> Result<Facts, DeviceError> {
        self.0.about().await
    }
    pub async fn condition(&mut self) -> Result<Facts, DeviceError> {
        self.0.condition().await
    }
}

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
}

/// [`GazeSource`] and [`About`] in a form that can be boxed.
pub trait DynGaze: About {
    fn rate_hz(&self) -> f32;
    fn next_sample(&mut self) -> BoxFuture<'_, Result<GazeSample, DeviceError>>;
}

impl<T: GazeSource + About> DynGaze for T {
    fn rate_hz(&self) -> f32 {
        GazeSource::rate_hz(self)
    }
    fn next_sample(&mut self) -> BoxFuture<'_, Result<GazeSample, DeviceError>> {
        Box::pin(GazeSource::next_sample(self))
    }
}

/// Any eye-tracker driver.
pub struct BoxGaze(pub Box<dyn DynGaze>);

impl BoxGaze {
    pub fn identity(&self) -> String {
        self.0.identity()
    }
    pub async fn about(&mut self) -> Result<Facts, DeviceError> {
        self.0.about().await
    }
}

impl GazeSource for BoxGaze {
    fn rate_hz(&self) -> f32 {
        self.0.rate_hz()
    }
    fn next_sample(&mut self) -> impl Future<Output = Result<GazeSample, DeviceError>> + Send {
        self.0.next_sample()
    }
}

/// [`PlaneSequencer`], [`About`] and [`Resume`] in a form that can be boxed.
pub trait DynSequencer: About + Resume {
    fn program<'a>(
        &'a mut self,
        schedule: &'a PlaneSchedule,
    ) -> BoxFuture<'a, Result<(), DeviceError>>;
    fn start(&mut self) -> BoxFuture<'_, Result<(), DeviceError>>;
    fn stop(&mut self) -> BoxFuture<'_, Result<(), DeviceError>>;
    fn next_event(&mut self) -> BoxFuture<'_, Result<SequencerEvent, DeviceError>>;
}

impl<T: PlaneSequencer + About + Resume> DynSequencer for T {
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

impl BoxSequencer {
    pub fn identity(&self) -> String {
        self.0.identity()
    }
    pub async fn about(&mut self) -> Result<Facts, DeviceError> {
        self.0.about().await
    }
    /// Whether [`BoxSequencer::resume`] can restore the session on a new link.
    pub fn resumes(&self) -> bool {
        self.0.resumes()
    }
    /// Restores the session (schedule, running or not) on a new link after an unplug.
    pub async fn resume(&mut self, link: Link) -> Result<(), DeviceError> {
        self.0.resume(link).await
    }
}

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
