//! Several tools in one session (issue 50): which tool slot a `DeviceLink` stream takes. A
//! session has `SoftBody::max_tools()` slots (the scene's `probe.max_tools`, default 2, at most
//! `haptic_model::body::MAX_TOOLS`); a stream names its tool in its first sample's `tool_id`
//! ("" = the default tool). A tool the scene names (`[[probe.tool]] id`, answered by
//! `SoftBody::tool_slot`) takes its own slot; any other takes the lowest free slot no named tool
//! reserves. Pure functions: the session ([`crate::session::Session::attach_tool`]) holds the
//! lock and the slots.

use crate::error::ServerError;

/// A tool a scene names (`[[probe.tool]]`): its id and its own probe parameters, where given.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NamedTool {
    /// The tool id (`id`).
    pub id: String,
    /// Its probe radius (`radius_m`), m.
    pub radius_m: Option<f64>,
    /// Its force limit (`max_force_n`), N.
    pub max_force_n: Option<f64>,
}

impl NamedTool {
    /// A named tool without parameters of its own.
    pub fn id(id: &str) -> Self {
        Self {
            id: id.to_owned(),
            ..Self::default()
        }
    }
}

/// The tools `scene` names (`[[probe.tool]]`, parsed and checked by the model's scene
/// parser), with their own probe radius and force limit: the candidates for
/// `SoftBody::tool_slot`, and the parameters frames and link headers show per tool.
pub fn scene_tools(scene: &haptic_model::scene::Scene) -> Vec<NamedTool> {
    scene
        .tools
        .named
        .iter()
        .map(|t| NamedTool {
            id: t.id.clone(),
            radius_m: Some(t.probe.radius_m),
            max_force_n: Some(t.probe.max_force_n),
        })
        .collect()
}

/// Longest tool id accepted, bytes.
pub const MAX_TOOL_ID_BYTES: usize = 64;

/// Whether `c` may appear in a tool id: ASCII letters and digits, `-`, `_`, `.`, `:` (ids show
/// in tables, metrics labels and the web page as they are).
pub fn tool_id_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.' | ':')
}

/// Checks a stream's tool id.
///
/// # Errors
/// [`ServerError::InvalidArgument`] for an id longer than [`MAX_TOOL_ID_BYTES`] or with a
/// character [`tool_id_char`] refuses.
pub fn check_tool_id(id: &str) -> Result<(), ServerError> {
    if id.len() > MAX_TOOL_ID_BYTES || !id.chars().all(tool_id_char) {
        return Err(ServerError::InvalidArgument(format!(
            "tool_id must be at most {MAX_TOOL_ID_BYTES} ASCII letters, digits, '-', '_', '.' \
             or ':'"
        )));
    }
    Ok(())
}

/// The slot tool `id` takes in session `session`, given the named tools' slots (`named`: id,
/// slot) and the ids of the streams connected now (`occupied[k]`: slot `k`'s, `None` when
/// free).
///
/// # Errors
/// [`ServerError::FailedPrecondition`] when a stream of the same tool id is connected (one
/// stream per tool, as one device per session before issue 50);
/// [`ServerError::Exhausted`] when no slot is free for it (the session's limit, or the only
/// free slots are reserved for named tools).
pub fn choose_slot(
    session: &str,
    id: &str,
    named: &[(String, usize)],
    occupied: &[Option<String>],
) -> Result<usize, ServerError> {
    if occupied.iter().any(|o| o.as_deref() == Some(id)) {
        return Err(ServerError::FailedPrecondition(if id.is_empty() {
            format!("session {session} already has a device connected (the default tool)")
        } else {
            format!("session {session} already has tool {id:?} connected")
        }));
    }
    if let Some(&(_, k)) = named.iter().find(|(n, k)| n == id && *k < occupied.len()) {
        // Unnamed tools never take a reserved slot, and the same id is not connected.
        return Ok(k);
    }
    let reserved = |k: usize| named.iter().any(|&(_, r)| r == k);
    (0..occupied.len())
        .find(|&k| occupied[k].is_none() && !reserved(k))
        .ok_or_else(|| {
            ServerError::Exhausted(format!(
                "session {session} takes at most {} tools at once (the scene's probe.max_tools) \
                 and has no free slot for tool {id:?}",
                occupied.len()
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn occ(ids: &[Option<&str>]) -> Vec<Option<String>> {
        ids.iter().map(|o| o.map(str::to_owned)).collect()
    }

    #[test]
    fn tools_take_the_lowest_free_slot_their_own_if_named_and_never_twice() {
        let none: Vec<(String, usize)> = Vec::new();
        assert_eq!(choose_slot("s", "", &none, &occ(&[None, None])).unwrap(), 0);
        assert_eq!(
            choose_slot("s", "right", &none, &occ(&[Some(""), None])).unwrap(),
            1
        );
        let e = choose_slot("s", "", &none, &occ(&[Some(""), None])).unwrap_err();
        assert!(matches!(e, ServerError::FailedPrecondition(_)), "{e}");
        let e = choose_slot("s", "c", &none, &occ(&[Some("a"), Some("b")])).unwrap_err();
        assert!(
            matches!(&e, ServerError::Exhausted(m) if m.contains("at most 2 tools")),
            "{e}"
        );
        // A named tool takes its slot; others skip it.
        let named = vec![("right".to_owned(), 0)];
        assert_eq!(
            choose_slot("s", "", &named, &occ(&[None, None])).unwrap(),
            1
        );
        assert_eq!(
            choose_slot("s", "right", &named, &occ(&[None, Some("")])).unwrap(),
            0
        );
        let e = choose_slot("s", "x", &named, &occ(&[None, Some("")])).unwrap_err();
        assert!(matches!(e, ServerError::Exhausted(_)), "{e}");
        // A one-slot session: a second default tool is refused as before issue 50.
        let e = choose_slot("s", "", &none, &occ(&[Some("")])).unwrap_err();
        assert!(matches!(e, ServerError::FailedPrecondition(_)), "{e}");
    }

    #[test]
    fn the_tools_a_scene_names_come_with_their_parameters() {
        let base = haptic_model::scene::builtin_scene_toml("lv").expect("lv");
        let text = format!(
            "{base}\n[[probe.tool]]\nid = \"left\"\nradius_m = 0.003\nmax_force_n = 2.0\n\
             [[probe.tool]]\nid = \"right\"\n"
        );
        let scene = haptic_model::scene::parse_scene_toml(&text, std::path::Path::new("."))
            .expect("the lv scene with two named tools");
        let tools = scene_tools(&scene);
        assert_eq!(tools.len(), 2);
        assert_eq!(
            tools[0],
            NamedTool {
                id: "left".into(),
                radius_m: Some(0.003),
                max_force_n: Some(2.0),
            }
        );
        // Unnamed parameters are the scene's `[probe]`.
        assert_eq!(tools[1].id, "right");
        assert_eq!(tools[1].radius_m, Some(scene.probe.radius_m));
        assert_eq!(tools[1].max_force_n, Some(scene.probe.max_force_n));
        let lv = haptic_model::scene::load_builtin("lv").expect("lv");
        assert!(
            scene_tools(&lv).is_empty(),
            "the built-in lv names no tools"
        );
    }

    #[test]
    fn tool_ids_are_short_and_plain() {
        assert!(check_tool_id("").is_ok() && check_tool_id("left-2.a_b:c").is_ok());
        assert!(check_tool_id(&"x".repeat(64)).is_ok());
        assert!(check_tool_id(&"x".repeat(65)).is_err());
        for bad in ["a\u{1b}[31m", "a b", "a\"b", "gauche\u{e9}"] {
            assert!(check_tool_id(bad).is_err(), "{bad:?}");
        }
    }
}
