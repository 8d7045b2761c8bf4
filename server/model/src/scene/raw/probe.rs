//! The `[probe]` section.

use super::*;

/// The raw `[probe]` section (empty when absent) and its probe ([`build_probe`]).
pub(super) fn probe_section(p: Option<RawProbe>) -> Result<(RawProbe, ProbeParams), ModelError> {
    let p = p.unwrap_or_default();
    let params = build_probe(&p)?;
    Ok((p, params))
}

/// The probe section (every integrator carries every contact model:
/// [`crate::integrate::resolve_contact_model`]).
pub(super) fn build_probe(p: &RawProbe) -> Result<ProbeParams, ModelError> {
    let d = ProbeParams::default();
    let contact = match p.contact.as_deref() {
        None => d.contact,
        Some(name) => ContactModel::from_name(name).ok_or_else(|| {
            ModelError::field(
                "probe.contact",
                format!(
                    "unknown contact model {:?}: expected \"auto\", \"sphere\", \"patch\", \"patch-hertz\" or \"patch-local\"",
                    name.chars().take(40).collect::<String>()
                ),
            )
        })?,
    };
    let params = ProbeParams {
        contact,
        radius_m: positive("probe.radius_m", p.radius_m.unwrap_or(d.radius_m))?,
        coupling_stiffness_n_per_m: positive(
            "probe.coupling_stiffness_n_per_m",
            p.coupling_stiffness_n_per_m
                .unwrap_or(d.coupling_stiffness_n_per_m),
        )?,
        coupling_damping_n_s_per_m: non_negative(
            "probe.coupling_damping_n_s_per_m",
            p.coupling_damping_n_s_per_m
                .unwrap_or(d.coupling_damping_n_s_per_m),
        )?,
        max_force_n: positive("probe.max_force_n", p.max_force_n.unwrap_or(d.max_force_n))?,
        friction_coefficient: checked(
            "probe.friction_coefficient",
            p.friction_coefficient.unwrap_or(d.friction_coefficient),
            |mu| (0.0..=10.0).contains(&mu),
            "in [0, 10]",
        )?,
        hertz_modulus_pa: d.hertz_modulus_pa,
    };
    Ok(params)
}

/// Why a scene of `family` takes one tool only (`None`: it takes several). Every family takes
/// several since issue 50: a following active region covers every tool
/// ([`crate::integrate::follow`]), the mass-spring surface subdivides under each.
pub(super) fn one_tool_reason(family: ModelFamily) -> Option<&'static str> {
    match family {
        ModelFamily::Fem | ModelFamily::Hybrid | ModelFamily::MassSpring => None,
    }
}

/// `[probe] max_tools` and `[[probe.tool]]` (module documentation of [`crate::scene`]): the
/// named tools' probes are `probe` with their overrides. `one_tool`: why the body takes one
/// tool only (then the default is 1 and more is refused with that reason).
pub(super) fn build_tools(
    p: &RawProbe,
    probe: ProbeParams,
    one_tool: Option<&'static str>,
) -> Result<ToolSpec, ModelError> {
    let max_tools = match (p.max_tools, one_tool) {
        (None, None) => DEFAULT_MAX_TOOLS,
        (None, Some(_)) => 1,
        (Some(n), _) => int_in("probe.max_tools", n, 1, MAX_TOOLS as i64)?,
    };
    if let (true, Some(why)) = (max_tools > 1, one_tool) {
        return Err(ModelError::field(
            "probe.max_tools",
            format!("must be 1 here, got {max_tools}: {why}"),
        ));
    }
    let raw_tools = p.tool.as_deref().unwrap_or_default();
    if raw_tools.len() > max_tools {
        return Err(ModelError::field(
            "probe.tool",
            format!(
                "{} named tools for max_tools = {max_tools}: name at most max_tools tools (or raise probe.max_tools, at most {MAX_TOOLS})",
                raw_tools.len()
            ),
        ));
    }
    let mut named: Vec<NamedTool> = Vec::with_capacity(raw_tools.len());
    for (k, t) in raw_tools.iter().enumerate() {
        let field = |name: &str| format!("probe.tool[{k}].{name}");
        let id = required(&field("id"), t.id.clone())?;
        tool_id_rules(&field("id"), &id)?;
        if named.iter().any(|n| n.id == id) {
            return Err(ModelError::field(
                field("id"),
                format!("{id:?} names an earlier tool too: tool ids must be unique"),
            ));
        }
        let mut params = probe;
        if let Some(r) = t.radius_m {
            params.radius_m = positive(&field("radius_m"), r)?;
        }
        if let Some(f) = t.max_force_n {
            params.max_force_n = positive(&field("max_force_n"), f)?;
        }
        named.push(NamedTool { id, probe: params });
    }
    Ok(ToolSpec { max_tools, named })
}

/// A tool id is non-empty, at most [`MAX_TOOL_ID_CHARS`] characters, without control
/// characters.
fn tool_id_rules(field: &str, id: &str) -> Result<(), ModelError> {
    let chars = id.chars().count();
    if chars == 0 || chars > MAX_TOOL_ID_CHARS {
        return Err(ModelError::field(
            field,
            format!("must have 1..={MAX_TOOL_ID_CHARS} characters, got {chars}"),
        ));
    }
    if id.chars().any(char::is_control) {
        return Err(ModelError::field(field, "holds a control character"));
    }
    Ok(())
}
