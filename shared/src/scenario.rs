//! Scenario files: a world, the drone slots with their homes, targets and scripted faults.
//!
//! Written in TOML with unknown fields rejected. The paper's city and the lab map of the
//! real-flight test are built in ([`Scenario::builtin`]) so no file is needed at run time.

use crate::geometry::{Matrix3, Vec3};
use crate::ids::{DroneId, IdError};
use crate::world::{Bounds, Ellipsoid, EllipsoidError, Landmark, LandmarkKind, World};
use serde::{Deserialize, Serialize};
use std::collections::HashSet;

const CITY: &str = include_str!("../scenarios/city.toml");
const LAB: &str = include_str!("../scenarios/lab.toml");

/// Names of the built-in scenarios.
pub const BUILTIN: [&str; 2] = ["city", "lab"];

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScenarioError {
    #[error("scenario file: {0}")]
    Syntax(String),
    #[error("unknown built-in scenario {0:?} (known: city, lab)")]
    UnknownBuiltin(String),
    #[error("bounds: min must be below max on every axis")]
    BadBounds,
    #[error(transparent)]
    Obstacle(#[from] EllipsoidError),
    #[error("obstacle {0}: give exactly one of `semi_axes` or `matrix`")]
    ObstacleShape(String),
    #[error("landmark {name} at ({x:.1}, {y:.1}, {z:.1}) is outside the bounds", x = .position.x, y = .position.y, z = .position.z)]
    LandmarkOutOfBounds { name: String, position: Vec3 },
    #[error("drone {id}'s home is outside the bounds or inside an obstacle")]
    BadHome { id: String },
    #[error("the name {0:?} is used twice")]
    DuplicateName(String),
    #[error("bad drone id: {0}")]
    BadId(#[from] IdError),
    #[error("target {target} hides at {landmark:?}, which is not a landmark")]
    UnknownLandmark { target: String, landmark: String },
    #[error("target {0}: give exactly one of `start` or `hidden_at`")]
    TargetPlacement(String),
    #[error("target {0}: a waypoint path needs at least one point and a positive speed")]
    BadMotion(String),
    #[error("fault at {at_s} s names drone {drone}, which the scenario does not have")]
    UnknownDrone { drone: String, at_s: f64 },
    #[error("{0} must be finite and positive")]
    NotPositive(&'static str),
}

/// How a target moves in the simulator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum TargetMotion {
    Static,
    /// Through `points` at `speed`, looping back to the start when `looped`.
    Waypoints {
        points: Vec<Vec3>,
        speed: f64,
        #[serde(default)]
        looped: bool,
    },
    /// Runs away from the nearest drone within `flee_radius`, at up to `speed`, inside the bounds.
    Evasive {
        speed: f64,
        flee_radius: f64,
    },
    /// Constant velocity (m/s), bouncing off the bounds.
    ConstantVelocity {
        velocity: Vec3,
    },
}

#[derive(Debug, Clone, PartialEq)]
pub struct TargetSpec {
    pub name: String,
    pub kind: String,
    pub start: Vec3,
    /// When set, the target hides at this landmark and is only reported as a detection when a
    /// drone passes close above it (the perception stand-in); otherwise it is published on
    /// `world/targets`.
    pub hidden_at: Option<String>,
    pub motion: TargetMotion,
    /// Seconds of simulation after which a visible target is no longer observed (it drove into
    /// a tunnel): how a tracker's loss of its target is exercised. `None`: always observed.
    pub observed_until_s: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// The vehicle stops answering for good (power loss): no heartbeat, no telemetry.
    VehicleDies,
    /// The MAVLink link drops for `duration_s` (both directions), then returns.
    LinkDrops { duration_s: f64 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultSpec {
    /// Seconds after the simulation starts.
    pub at_s: f64,
    pub drone: String,
    pub kind: FaultKind,
}

#[derive(Debug, Clone, PartialEq)]
pub struct DroneSlot {
    pub id: DroneId,
    /// The vehicle's home (its NED origin), world ENU.
    pub home: Vec3,
}

/// Required vertical separation / required horizontal separation between two drones: a drone's
/// downwash reaches further below it than its wake reaches sideways. The onboard planner and the
/// ground's choice of goal points use the same figure.
pub const DOWNWASH_FACTOR: f64 = 2.0;

/// Tuning that the scenario fixes for every drone in it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlightLimits {
    pub takeoff_altitude: f64,
    pub max_speed: f64,
    pub max_accel: f64,
    /// Radius of one drone (obstacles are inflated by it, separation is twice it).
    pub drone_radius: f64,
    /// Minimum centre-to-centre distance between two drones.
    pub safety_distance: f64,
    /// How close (horizontally) above a hidden target a drone must pass to detect it.
    pub detection_radius: f64,
    /// Highest altitude at which detection works.
    pub detection_altitude: f64,
    /// Fastest climb the autopilot flies, m/s: PX4's MPC_Z_VEL_MAX_UP (default 3 m/s), which
    /// PX4 enforces whatever the setpoint asks, so the planner must not plan beyond it.
    #[serde(default = "px4_max_climb_rate")]
    pub max_climb_rate: f64,
    /// Fastest descent, m/s: PX4's MPC_Z_VEL_MAX_DN (default 1.5 m/s).
    #[serde(default = "px4_max_descent_rate")]
    pub max_descent_rate: f64,
}

fn px4_max_climb_rate() -> f64 {
    3.0
}

fn px4_max_descent_rate() -> f64 {
    1.5
}

#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    pub name: String,
    pub description: String,
    pub limits: FlightLimits,
    pub world: World,
    pub drones: Vec<DroneSlot>,
    pub targets: Vec<TargetSpec>,
    pub faults: Vec<FaultSpec>,
}

fn positive(value: f64) -> bool {
    value.is_finite() && value > 0.0
}

// ---- file format -------------------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileScenario {
    name: String,
    #[serde(default)]
    description: String,
    limits: FlightLimits,
    bounds: FileBounds,
    #[serde(default)]
    obstacles: Vec<FileObstacle>,
    #[serde(default)]
    landmarks: Vec<FileLandmark>,
    #[serde(default)]
    drones: Vec<FileDrone>,
    #[serde(default)]
    targets: Vec<FileTarget>,
    #[serde(default)]
    faults: Vec<FaultSpec>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileBounds {
    min: [f64; 3],
    max: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileObstacle {
    name: String,
    center: [f64; 3],
    semi_axes: Option<[f64; 3]>,
    #[serde(default)]
    yaw_deg: f64,
    matrix: Option<[[f64; 3]; 3]>,
    /// Also list the obstacle as a landmark of this kind (skyscrapers are both).
    landmark: Option<LandmarkKind>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileLandmark {
    name: String,
    kind: LandmarkKind,
    position: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileDrone {
    id: String,
    home: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileTarget {
    name: String,
    #[serde(default = "default_target_kind")]
    kind: String,
    start: Option<[f64; 3]>,
    hidden_at: Option<String>,
    #[serde(default = "static_motion")]
    motion: TargetMotion,
    observed_until_s: Option<f64>,
}

fn default_target_kind() -> String {
    "person".into()
}

fn static_motion() -> TargetMotion {
    TargetMotion::Static
}

impl Scenario {
    /// One of the built-in scenarios by name (`city`, `lab`).
    pub fn builtin(name: &str) -> Result<Scenario, ScenarioError> {
        match name {
            "city" => Scenario::from_toml(CITY),
            "lab" => Scenario::from_toml(LAB),
            other => Err(ScenarioError::UnknownBuiltin(other.to_owned())),
        }
    }

    /// Parses and validates a scenario.
    pub fn from_toml(text: &str) -> Result<Scenario, ScenarioError> {
        let file: FileScenario =
            toml::from_str(text).map_err(|e| ScenarioError::Syntax(e.to_string()))?;
        let l = file.limits;
        for (value, what) in [
            (l.takeoff_altitude, "limits.takeoff_altitude"),
            (l.max_speed, "limits.max_speed"),
            (l.max_accel, "limits.max_accel"),
            (l.drone_radius, "limits.drone_radius"),
            (l.safety_distance, "limits.safety_distance"),
            (l.detection_radius, "limits.detection_radius"),
            (l.detection_altitude, "limits.detection_altitude"),
            (l.max_climb_rate, "limits.max_climb_rate"),
            (l.max_descent_rate, "limits.max_descent_rate"),
        ] {
            if !positive(value) {
                return Err(ScenarioError::NotPositive(what));
            }
        }
        let bounds = Bounds {
            min: Vec3::from(file.bounds.min),
            max: Vec3::from(file.bounds.max),
        };
        if !(0..3).all(|i| {
            bounds.min[i].is_finite() && bounds.max[i].is_finite() && bounds.min[i] < bounds.max[i]
        }) {
            return Err(ScenarioError::BadBounds);
        }

        let mut names = HashSet::new();
        let mut claim = |name: &str| {
            if names.insert(name.to_owned()) {
                Ok(())
            } else {
                Err(ScenarioError::DuplicateName(name.to_owned()))
            }
        };

        let mut obstacles = Vec::new();
        let mut landmarks = Vec::new();
        for o in file.obstacles {
            claim(&o.name)?;
            let center = Vec3::from(o.center);
            let ellipsoid = match (o.semi_axes, o.matrix) {
                (Some(axes), None) => Ellipsoid::from_semi_axes(
                    &o.name,
                    center,
                    Vec3::from(axes),
                    o.yaw_deg.to_radians(),
                )?,
                (None, Some(m)) => {
                    let shape = Matrix3::from_fn(|r, c| m[r][c]);
                    Ellipsoid::new(&o.name, center, shape)?
                }
                _ => return Err(ScenarioError::ObstacleShape(o.name)),
            };
            if let Some(kind) = o.landmark {
                landmarks.push(Landmark {
                    name: o.name.clone(),
                    kind,
                    position: center,
                });
            }
            obstacles.push(ellipsoid);
        }
        for lm in file.landmarks {
            claim(&lm.name)?;
            landmarks.push(Landmark {
                name: lm.name,
                kind: lm.kind,
                position: Vec3::from(lm.position),
            });
        }
        for lm in &landmarks {
            if !bounds.contains(&lm.position) {
                return Err(ScenarioError::LandmarkOutOfBounds {
                    name: lm.name.clone(),
                    position: lm.position,
                });
            }
        }
        let world = World {
            bounds,
            obstacles,
            landmarks,
        };

        let mut drones = Vec::new();
        for d in file.drones {
            claim(&d.id)?;
            let id = DroneId::new(&d.id)?;
            let home = Vec3::from(d.home);
            if world.check_point(&home, l.drone_radius).is_err() {
                return Err(ScenarioError::BadHome { id: d.id });
            }
            drones.push(DroneSlot { id, home });
        }

        let mut targets = Vec::new();
        for t in file.targets {
            claim(&t.name)?;
            let start = match (&t.start, &t.hidden_at) {
                (Some(p), None) => Vec3::from(*p),
                (None, Some(at)) => match world.landmark(at) {
                    Some(lm) => lm.position,
                    None => {
                        return Err(ScenarioError::UnknownLandmark {
                            target: t.name,
                            landmark: at.clone(),
                        });
                    }
                },
                _ => return Err(ScenarioError::TargetPlacement(t.name)),
            };
            match &t.motion {
                TargetMotion::Waypoints { points, speed, .. }
                    if points.is_empty() || !positive(*speed) =>
                {
                    return Err(ScenarioError::BadMotion(t.name));
                }
                TargetMotion::Evasive { speed, flee_radius }
                    if !(positive(*speed) && positive(*flee_radius)) =>
                {
                    return Err(ScenarioError::BadMotion(t.name));
                }
                _ => {}
            }
            targets.push(TargetSpec {
                name: t.name,
                kind: t.kind,
                start,
                hidden_at: t.hidden_at,
                motion: t.motion,
                observed_until_s: t.observed_until_s,
            });
        }

        for f in &file.faults {
            if !drones.iter().any(|d| d.id.as_str() == f.drone) {
                return Err(ScenarioError::UnknownDrone {
                    drone: f.drone.clone(),
                    at_s: f.at_s,
                });
            }
        }

        Ok(Scenario {
            name: file.name,
            description: file.description,
            limits: l,
            world,
            drones,
            targets,
            faults: file.faults,
        })
    }

    /// The first `n` drone slots, or an error naming how many the scenario has.
    pub fn first_drones(&self, n: usize) -> Result<&[DroneSlot], String> {
        self.drones.get(..n).ok_or_else(|| {
            format!(
                "scenario {} has {} drone slots; {n} asked for",
                self.name,
                self.drones.len()
            )
        })
    }

    pub fn drone(&self, id: &DroneId) -> Option<&DroneSlot> {
        self.drones.iter().find(|d| &d.id == id)
    }

    /// Every drone slot's id, in the map's order.
    pub fn slot_ids(&self) -> Vec<String> {
        self.drones.iter().map(|d| d.id.to_string()).collect()
    }

    /// The names a goto or a chase may give: the landmarks', then the targets'.
    pub fn place_names(&self) -> Vec<String> {
        let landmarks = self.world.landmarks.iter().map(|l| l.name.clone());
        landmarks
            .chain(self.targets.iter().map(|t| t.name.clone()))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
name = "t"
[limits]
takeoff_altitude = 5.0
max_speed = 5.0
max_accel = 3.0
drone_radius = 0.5
safety_distance = 2.0
detection_radius = 4.0
detection_altitude = 15.0
[bounds]
min = [-50.0, -50.0, 0.0]
max = [50.0, 50.0, 40.0]
[[obstacles]]
name = "tower"
center = [0.0, 0.0, 0.0]
semi_axes = [5.0, 5.0, 30.0]
landmark = "skyscraper"
[[landmarks]]
name = "car_1"
kind = "car"
position = [20.0, 0.0, 0.0]
[[drones]]
id = "alfa"
home = [-20.0, -20.0, 0.0]
[[targets]]
name = "suspect"
hidden_at = "car_1"
[[faults]]
at_s = 10.0
drone = "alfa"
kind = "vehicle_dies"
"#;

    #[test]
    fn minimal_scenario_loads() {
        let s = Scenario::from_toml(MINIMAL).expect("valid");
        assert_eq!(s.world.landmarks.len(), 2);
        assert_eq!(s.world.obstacles.len(), 1);
        assert_eq!(s.targets[0].start, Vec3::new(20.0, 0.0, 0.0));
    }

    fn broken(from: &str, to: &str) -> ScenarioError {
        let text = MINIMAL.replacen(from, to, 1);
        assert_ne!(text, MINIMAL, "replacement {from:?} did not apply");
        Scenario::from_toml(&text).expect_err("should be rejected")
    }

    #[test]
    fn unknown_fields_are_rejected() {
        let e = broken(
            "semi_axes = [5.0, 5.0, 30.0]",
            "semi_axes = [5.0, 5.0, 30.0]\ncolour = \"red\"",
        );
        assert!(
            matches!(&e, ScenarioError::Syntax(m) if m.contains("colour")),
            "{e}"
        );
    }

    #[test]
    fn non_positive_definite_ellipsoid_is_rejected() {
        let e = broken(
            "semi_axes = [5.0, 5.0, 30.0]",
            "matrix = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]",
        );
        assert!(
            matches!(
                e,
                ScenarioError::Obstacle(EllipsoidError::NotPositiveDefinite(_))
            ),
            "{e}"
        );
    }

    #[test]
    fn landmark_outside_bounds_is_rejected() {
        let e = broken("position = [20.0, 0.0, 0.0]", "position = [80.0, 0.0, 0.0]");
        assert!(
            matches!(e, ScenarioError::LandmarkOutOfBounds { .. }),
            "{e}"
        );
    }

    #[test]
    fn duplicate_names_are_rejected() {
        let e = broken("name = \"car_1\"", "name = \"tower\"");
        assert_eq!(e, ScenarioError::DuplicateName("tower".into()));
    }

    #[test]
    fn unknown_references_are_rejected() {
        let e = broken("hidden_at = \"car_1\"", "hidden_at = \"car_9\"");
        assert!(matches!(e, ScenarioError::UnknownLandmark { .. }), "{e}");
        let e = broken("drone = \"alfa\"", "drone = \"zulu\"");
        assert!(matches!(e, ScenarioError::UnknownDrone { .. }), "{e}");
        let e = broken("home = [-20.0, -20.0, 0.0]", "home = [0.0, 0.0, 0.0]");
        assert!(matches!(e, ScenarioError::BadHome { .. }), "{e}");
    }

    #[test]
    fn the_city_matches_the_paper() {
        let city = Scenario::builtin("city").expect("city is valid");
        let count = |k: LandmarkKind| city.world.landmarks.iter().filter(|l| l.kind == k).count();
        assert_eq!(city.world.landmarks.len(), 51);
        assert_eq!(count(LandmarkKind::Car), 15);
        assert_eq!(count(LandmarkKind::Villa), 10);
        assert_eq!(count(LandmarkKind::Tree), 20);
        assert_eq!(count(LandmarkKind::Skyscraper), 4);
        assert_eq!(count(LandmarkKind::Pad), 2);
        assert_eq!(city.world.obstacles.len(), 4);
        assert!(city.drones.len() >= 20);
    }

    #[test]
    fn the_lab_matches_the_real_flight_test() {
        let lab = Scenario::builtin("lab").expect("lab is valid");
        let ids: Vec<_> = lab.drones.iter().map(|d| d.id.as_str()).collect();
        assert_eq!(ids, ["alfa", "bravo", "charlie"]);
        for name in [
            "small_park",
            "large_park_north",
            "large_park_south",
            "villa",
            "business_district",
        ] {
            assert!(lab.world.landmark(name).is_some(), "{name}");
        }
    }
}
