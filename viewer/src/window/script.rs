//! The window's input script: synthetic events and waits (`frames N`, `converge`, `drag`,
//! `wheel`, `key`, `resize`, `screenshot`, `signal`, `await`, `lose-device`, `quit`) that a
//! front-end runs through the same handlers as real events, for tests and demos.

use super::controls::{Input, KeyPress};
use super::{Result, WindowError};
use std::path::PathBuf;

fn invalid(message: String) -> WindowError {
    WindowError::Invalid(message)
}

/// Returns an [`WindowError::Invalid`] with a formatted message.
macro_rules! fail {
    ($($arg:tt)*) => {
        return Err(invalid(format!($($arg)*)))
    };
}

/// One script command.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Wait until N more frames are drawn.
    Frames(u64),
    /// Wait until the view has converged.
    Converge,
    /// Wait until a playing time series has moved on N times in all.
    Played(u64),
    /// Feed these events through the input handlers.
    Inputs(Vec<Input>),
    /// Ask for this window size and wait until it is granted (or 100 frames).
    Resize(u32, u32),
    /// Save the shown image as a PNG.
    Screenshot(PathBuf),
    /// Create this file.
    Signal(PathBuf),
    /// Wait until this file exists.
    Await(PathBuf),
    /// Destroy the graphics device, as a driver reset would.
    LoseDevice,
    /// Close the window.
    Quit,
}

/// The synthetic input script.
#[derive(Debug, Default)]
pub struct Script {
    /// The commands still to run, the current one first.
    pub commands: std::collections::VecDeque<Command>,
    /// Frames drawn when the current `frames N` or `resize` started.
    pub waiting_since: Option<u64>,
}

fn point(s: &str) -> Result<(f64, f64)> {
    let (x, y) = s
        .split_once(',')
        .ok_or_else(|| invalid(format!("expected X,Y, got {s:?}")))?;
    let number = |t: &str| {
        t.trim()
            .parse::<f64>()
            .map_err(|e| invalid(format!("script: {e} in {s:?}")))
    };
    let p = (number(x)?, number(y)?);
    if !p.0.is_finite() || !p.1.is_finite() {
        fail!("coordinates must be finite, got {s:?}");
    }
    Ok(p)
}

impl Script {
    /// Parses commands separated by `;` or new lines.
    pub fn parse(text: &str) -> Result<Script> {
        let mut commands = std::collections::VecDeque::new();
        for raw in text.split([';', '\n']) {
            let words: Vec<&str> = raw.split_whitespace().collect();
            let Some((&verb, rest)) = words.split_first() else {
                continue;
            };
            let one = || -> Result<&str> {
                match rest {
                    [x] => Ok(x),
                    _ => fail!("script: `{verb}` takes one argument, in {raw:?}"),
                }
            };
            let c = match verb {
                "frames" => Command::Frames(
                    one()?
                        .parse()
                        .map_err(|e| invalid(format!("script: frames N: {e}")))?,
                ),
                "converge" => Command::Converge,
                "played" => Command::Played(
                    one()?
                        .parse()
                        .map_err(|e| invalid(format!("script: played N: {e}")))?,
                ),
                "drag" => {
                    // drag X0,Y0 X1,Y1 [shift] [over N]: the moves within one frame, or one a
                    // frame for N frames (a hand's drag, for measuring frames while turning).
                    let (points, shift, over) = match rest {
                        [a, b] => ((a, b), false, None),
                        [a, b, m] if *m == "shift" => ((a, b), true, None),
                        [a, b, o, n] if *o == "over" => ((a, b), false, Some(*n)),
                        [a, b, m, o, n] if *m == "shift" && *o == "over" => {
                            ((a, b), true, Some(*n))
                        }
                        _ => fail!("script: drag X0,Y0 X1,Y1 [shift] [over N], in {raw:?}"),
                    };
                    let (from, to) = (point(points.0)?, point(points.1)?);
                    let over = match over {
                        None => None,
                        Some(n) => match n.parse::<usize>() {
                            Ok(n) if n > 0 => Some(n),
                            _ => fail!(
                                "script: drag … over N takes a count of frames ≥ 1, got {n:?}"
                            ),
                        },
                    };
                    let start = vec![
                        Input::Shift(shift),
                        Input::CursorMoved(from.0, from.1),
                        Input::LeftButton(true),
                    ];
                    let steps = over.unwrap_or(8);
                    let moves = (1..=steps).map(|i| {
                        let t = i as f64 / steps as f64;
                        Input::CursorMoved(
                            from.0 + t * (to.0 - from.0),
                            from.1 + t * (to.1 - from.1),
                        )
                    });
                    let end = [Input::LeftButton(false), Input::Shift(false)];
                    match over {
                        None => {
                            Command::Inputs(start.into_iter().chain(moves).chain(end).collect())
                        }
                        Some(_) => {
                            commands.push_back(Command::Inputs(start));
                            for m in moves {
                                commands.push_back(Command::Inputs(vec![m]));
                                commands.push_back(Command::Frames(1));
                            }
                            Command::Inputs(end.to_vec())
                        }
                    }
                }
                "wheel" => {
                    let l: f64 = one()?
                        .parse()
                        .map_err(|e| invalid(format!("script: wheel LINES: {e}")))?;
                    if !l.is_finite() {
                        fail!("script: wheel needs a finite number");
                    }
                    Command::Inputs(vec![Input::Wheel(l)])
                }
                "key" => {
                    let k = one()?;
                    let key = match k.to_lowercase().as_str() {
                        "esc" | "escape" => KeyPress::Escape,
                        "f1" => KeyPress::Help,
                        "left" => KeyPress::Left,
                        "right" => KeyPress::Right,
                        "space" => KeyPress::Char(' '),
                        s if s.chars().count() == 1 => {
                            KeyPress::Char(s.chars().next().unwrap_or('?'))
                        }
                        _ => fail!("script: unknown key {k:?}"),
                    };
                    Command::Inputs(vec![Input::Key(key)])
                }
                "resize" => {
                    let s = one()?;
                    let (w, h) = s
                        .split_once('x')
                        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
                        .ok_or_else(|| invalid(format!("script: resize WxH, got {s:?}")))?;
                    Command::Resize(w, h)
                }
                "screenshot" => Command::Screenshot(one()?.into()),
                "signal" => Command::Signal(one()?.into()),
                "await" => Command::Await(one()?.into()),
                "quit" => Command::Quit,
                "lose-device" => Command::LoseDevice,
                _ => fail!("script: unknown command {verb:?} in {raw:?}"),
            };
            commands.push_back(c);
        }
        Ok(Script {
            commands,
            waiting_since: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_script_parses_into_commands_and_a_drag_into_its_events() {
        let s =
            Script::parse("frames 3; drag 10,20 30,40 shift\nkey Esc; resize 64x48;quit").unwrap();
        let c: Vec<&Command> = s.commands.iter().collect();
        assert_eq!(c.len(), 5);
        assert_eq!(c[0], &Command::Frames(3));
        let Command::Inputs(drag) = c[1] else {
            panic!("a drag is input events, got {:?}", c[1]);
        };
        assert_eq!(drag.first(), Some(&Input::Shift(true)));
        assert_eq!(drag[1], Input::CursorMoved(10.0, 20.0));
        assert!(drag.contains(&Input::CursorMoved(30.0, 40.0)));
        assert_eq!(drag.last(), Some(&Input::Shift(false)));
        assert_eq!(c[2], &Command::Inputs(vec![Input::Key(KeyPress::Escape)]));
        assert_eq!(c[3], &Command::Resize(64, 48));
        assert_eq!(c[4], &Command::Quit);
        // Spread over frames: press, then one move and one frame each, then release.
        let s = Script::parse("drag 0,0 30,60 over 3").unwrap();
        let c: Vec<&Command> = s.commands.iter().collect();
        assert_eq!(c.len(), 1 + 2 * 3 + 1);
        assert_eq!(
            c[0],
            &Command::Inputs(vec![
                Input::Shift(false),
                Input::CursorMoved(0.0, 0.0),
                Input::LeftButton(true)
            ])
        );
        assert_eq!(c[1], &Command::Inputs(vec![Input::CursorMoved(10.0, 20.0)]));
        assert_eq!(c[2], &Command::Frames(1));
        assert_eq!(c[5], &Command::Inputs(vec![Input::CursorMoved(30.0, 60.0)]));
        assert_eq!(
            c[7],
            &Command::Inputs(vec![Input::LeftButton(false), Input::Shift(false)])
        );
    }

    #[test]
    fn a_bad_script_is_refused_with_the_reason() {
        for (text, says) in [
            ("frames x", "frames N"),
            ("drag 1,2", "drag X0,Y0 X1,Y1"),
            ("drag 1,2 3,4 over 0", "count of frames"),
            ("drag 1,2 3,4 shift over x", "count of frames"),
            ("drag 1,nan 2,3", "finite"),
            ("wheel inf", "finite"),
            ("key ctrl", "unknown key"),
            ("resize 64", "resize WxH"),
            ("jump 3", "unknown command"),
            ("frames 1 2", "takes one argument"),
        ] {
            let e = Script::parse(text).unwrap_err().to_string();
            assert!(e.contains(says), "{text:?}: {e}");
        }
    }
}
