//! Eye and camera rig geometry and the geometric gaze solver of Sec. A.4 (S9–S14).
