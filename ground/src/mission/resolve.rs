//! Turns a model's call into a concrete action: a landmark or a moving target named in a goto
//! becomes a point, at an altitude low enough for the perception stand-in to see what is there.

use tacos_prompts::{ActionName, Call};
use tacos_shared::Vec3;
use tacos_shared::action::Action;
use tacos_shared::messages::TargetObservation;
use tacos_shared::scenario::Scenario;

/// The altitude of a goto to a landmark: the take-off altitude, capped below the detection
/// altitude so a drone that visits a place can see a hidden target there.
pub fn inspect_altitude(scenario: &Scenario) -> f64 {
    let l = &scenario.limits;
    l.takeoff_altitude.min(0.8 * l.detection_altitude)
}

/// The action a call asks for, or why it names nothing that can be flown to.
pub fn resolve(
    call: &Call,
    scenario: &Scenario,
    visible: &[TargetObservation],
) -> Result<Action, String> {
    let altitude = inspect_altitude(scenario);
    match call.action {
        ActionName::ArmTakeoff => Ok(Action::ArmTakeoff),
        ActionName::StopTracking => Ok(Action::StopTracking),
        ActionName::Land => Ok(Action::Land),
        ActionName::Hold => Ok(Action::Hold),
        // A named place wins over coordinates: "goto small_park" is what the model meant, and
        // the numbers a small model writes beside a name are usually invented (the embedded
        // 135M model fills "xyz" with 1.0, 2.0, 3.0 whatever the target).
        ActionName::Goto => match (call.target_name(), call.xyz) {
            (None, Some([x, y, z])) => Ok(Action::Goto {
                target: Vec3::new(x, y, z),
            }),
            (Some(name), _) => {
                if let Some(l) = scenario.world.landmark(name) {
                    Ok(Action::Goto {
                        target: Vec3::new(l.position.x, l.position.y, l.position.z + altitude),
                    })
                } else if let Some(t) = visible.iter().find(|t| t.name == name) {
                    Ok(Action::Goto {
                        target: Vec3::new(t.position.x, t.position.y, t.position.z + altitude),
                    })
                } else {
                    Err(format!(
                        "goto target {name:?} is neither a landmark nor a visible target"
                    ))
                }
            }
            (None, None) => {
                Err("goto needs a landmark name in \"target\" or a point in \"xyz\"".into())
            }
        },
        ActionName::StartTracking => match call.target_name() {
            Some(name) if scenario.targets.iter().any(|t| t.name == name) => {
                Ok(Action::StartTracking {
                    target: name.to_owned(),
                })
            }
            Some(name) => Err(format!(
                "start_tracking: {name:?} is not a target (landmarks cannot be tracked)"
            )),
            None => Err("start_tracking needs a target name".into()),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn call(action: ActionName, target: &str, xyz: Option<[f64; 3]>) -> Call {
        Call {
            task: "T1".into(),
            drone: "alfa".into(),
            action,
            target: target.into(),
            xyz,
        }
    }

    #[test]
    fn landmarks_become_points_at_inspection_altitude() {
        let city = Scenario::builtin("city").expect("city");
        let car = city.world.landmark("car_7").expect("car_7").position;
        assert_eq!(
            resolve(&call(ActionName::Goto, "car_7", None), &city, &[]),
            Ok(Action::Goto {
                target: Vec3::new(car.x, car.y, 10.0)
            })
        );
        assert_eq!(
            resolve(
                &call(ActionName::Goto, "none", Some([1.0, 2.0, 3.0])),
                &city,
                &[]
            ),
            Ok(Action::Goto {
                target: Vec3::new(1.0, 2.0, 3.0)
            })
        );
        assert_eq!(
            resolve(
                &call(ActionName::Goto, "car_7", Some([1.0, 2.0, 3.0])),
                &city,
                &[]
            ),
            Ok(Action::Goto {
                target: Vec3::new(car.x, car.y, 10.0)
            }),
            "the name wins over invented coordinates"
        );
        assert!(resolve(&call(ActionName::Goto, "none", None), &city, &[]).is_err());
        assert!(resolve(&call(ActionName::Goto, "atlantis", None), &city, &[]).is_err());
        assert!(resolve(&call(ActionName::StartTracking, "car_7", None), &city, &[]).is_err());
        assert!(resolve(&call(ActionName::StartTracking, "van", None), &city, &[]).is_ok());
    }
}
