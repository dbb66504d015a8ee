//! What the content part publishes ([`ContentHandle`]): the content source and, on a stereo
//! layout, each eye's view of it; `/status`'s `content` and `eye_views`, and a source or
//! views failing now.

use std::sync::Arc;

use serde_json::{Map, Value};

use super::source::Content;
use super::stereo::EyeViews;
use crate::problem::Problem;

/// The content part's handle.
pub struct ContentHandle {
    source: Arc<dyn Content>,
    eye_views: Option<Arc<EyeViews>>,
}

impl ContentHandle {
    /// `eye_views`: a stereo layout's eyes.
    pub fn new(source: Arc<dyn Content>, eye_views: Option<Arc<EyeViews>>) -> Self {
        ContentHandle { source, eye_views }
    }

    /// What the rig shows (the API's frame endpoints reach a stream through it).
    pub fn source(&self) -> &Arc<dyn Content> {
        &self.source
    }

    /// A stereo layout: each eye's view of the content.
    pub fn eye_views(&self) -> Option<&Arc<EyeViews>> {
        self.eye_views.as_ref()
    }

    /// `/status`'s `content` and `eye_views`.
    pub fn status(&self, out: &mut Map<String, Value>) {
        out.insert("content".into(), self.source.status());
        out.insert(
            "eye_views".into(),
            self.eye_views.as_ref().map_or(Value::Null, |v| v.status()),
        );
    }

    pub fn problems(&self) -> Vec<Problem> {
        let mut p = self.source.problems();
        if let Some(v) = &self.eye_views {
            p.extend(v.problems());
        }
        p
    }
}
