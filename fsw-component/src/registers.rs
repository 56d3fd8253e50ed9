//! The node's Cyphal registers (`uavcan.register.Access` / `List`) and the register file.
//!
//! The registers are views of the component configuration: `uavcan.node.id`,
//! `uavcan.node.description`, `uavcan.sub|pub.<port>.id` and `.type` for every catalogue
//! message on CAN (names from `crate::cyphal_config::PORTS`), `uavcan.can.iface`,
//! `uavcan.can.mtu` (8 or 64), the telemetry source node-IDs and a few read-only settings
//! (`fsw.*`).
//!
//! Semantics (Cyphal v1.0 registers, as the ICD documents them):
//! - every value lives in a file (component.toml or the register file), so all are persistent;
//! - writes are possible only when `[cyphal] register_file` is set; a write is applied to a
//!   copy of the configuration the component will start with next, the whole copy is
//!   validated like component.toml, and only then is the register file rewritten (atomically:
//!   temporary file and rename) and the value kept. The running component is unchanged: a
//!   written value takes effect at the next start, and reads return it at once;
//! - a write that is refused (read-only register, wrong type, out-of-range or inconsistent
//!   value, file not writable) is answered with the unchanged value, as the service asks;
//! - an unknown name is answered with an empty value;
//! - numeric registers accept any single natural (`natural8`..`natural64`) and answer with
//!   their own type (`natural16` for IDs), so clients need not guess the width.
//!
//! The register file is TOML, one `"register.name" = value` per mutable register; at start
//! `apply_register_file` applies it over component.toml before validation, so its values
//! pass the same checks. A missing file is a first start (no overrides); an unknown or
//! read-only name, or a value of the wrong type, stops the start with the file's name.

use crate::config::{ComponentConfig, ConfigError};
use crate::cyphal_config::{Direction, PORTS};
use interfaces::cyphal::register::{Value, ValueKind};
use std::path::{Path, PathBuf};

/// An owned `uavcan.register.Value.1.0`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RegValue {
    pub kind: ValueKind,
    pub count: usize,
    pub raw: Vec<u8>,
}

impl RegValue {
    pub fn empty() -> Self {
        Self::from_value(&Value::EMPTY)
    }

    /// A string register; text beyond 256 bytes is cut at a character boundary (values
    /// come from validated configuration, so this does not happen in practice).
    pub fn string(text: &str) -> Self {
        let mut end = text.len().min(ValueKind::String.capacity());
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        let raw = text.as_bytes()[..end].to_vec();
        Self {
            kind: ValueKind::String,
            count: raw.len(),
            raw,
        }
    }

    pub fn natural16(n: u16) -> Self {
        Self::scalar(ValueKind::Natural16, &n.to_le_bytes())
    }

    pub fn natural32(n: u32) -> Self {
        Self::scalar(ValueKind::Natural32, &n.to_le_bytes())
    }

    pub fn natural64(n: u64) -> Self {
        Self::scalar(ValueKind::Natural64, &n.to_le_bytes())
    }

    fn scalar(kind: ValueKind, le: &[u8]) -> Self {
        Self {
            kind,
            count: 1,
            raw: le.to_vec(),
        }
    }

    pub fn from_value(value: &Value<'_>) -> Self {
        Self {
            kind: value.kind,
            count: value.count,
            raw: value.raw.to_vec(),
        }
    }

    pub fn as_value(&self) -> Value<'_> {
        // Constructors keep count and bytes consistent; the fallback is never taken.
        Value::new(self.kind, self.count, &self.raw).unwrap_or(Value::EMPTY)
    }

    /// The text of a string value.
    pub fn as_str(&self) -> Option<&str> {
        (self.kind == ValueKind::String)
            .then(|| std::str::from_utf8(&self.raw).ok())
            .flatten()
    }
}

/// What a register shows of the configuration.
#[derive(Clone, Copy, Debug)]
enum Field {
    NodeId,
    Description,
    CanIface,
    CanMtu,
    AocsNodeId,
    NavigationNodeId,
    /// `PORTS[i]`'s subject-ID.
    PortId(usize),
    /// `PORTS[i]`'s type name (read-only).
    PortType(usize),
    /// A read-only setting.
    Setting(fn(&ComponentConfig) -> RegValue),
}

fn natural_u16(value: &Value<'_>) -> Result<u16, String> {
    let n = value
        .as_natural()
        .ok_or_else(|| format!("want one natural number, got {:?}", value.kind))?;
    u16::try_from(n).map_err(|_| format!("{n} does not fit 16 bits"))
}

fn text(value: &Value<'_>) -> Result<String, String> {
    let owned = RegValue::from_value(value);
    owned
        .as_str()
        .map(str::to_owned)
        .ok_or_else(|| format!("want a UTF-8 string, got {:?}", value.kind))
}

impl Field {
    fn mutable(self) -> bool {
        !matches!(self, Self::PortType(_) | Self::Setting(_))
    }

    fn get(self, config: &ComponentConfig) -> RegValue {
        match self {
            Self::NodeId => RegValue::natural16(config.node.node_id.into()),
            Self::Description => RegValue::string(&config.node.description),
            Self::CanIface => RegValue::string(&config.can.interface),
            Self::CanMtu => RegValue::natural16(if config.can.fd { 64 } else { 8 }),
            Self::AocsNodeId => RegValue::natural16(config.cyphal.aocs_node_id),
            Self::NavigationNodeId => RegValue::natural16(config.cyphal.navigation_node_id),
            Self::PortId(i) => {
                RegValue::natural16(config.cyphal.subjects.get(i).unwrap_or(u16::MAX))
            }
            Self::PortType(i) => {
                RegValue::string(&PORTS.get(i).map_or(String::new(), |p| (p.type_name)()))
            }
            Self::Setting(get) => get(config),
        }
    }

    /// Sets the field from `value`; range and consistency are checked by the caller's
    /// validation of the whole configuration.
    fn set(self, config: &mut ComponentConfig, value: &Value<'_>) -> Result<(), String> {
        match self {
            Self::NodeId => {
                let id = natural_u16(value)?;
                config.node.node_id = u8::try_from(id).map_err(|_| format!("{id} > 127"))?;
            }
            Self::Description => config.node.description = text(value)?,
            Self::CanIface => config.can.interface = text(value)?,
            Self::CanMtu => {
                config.can.fd = match natural_u16(value)? {
                    8 => false,
                    64 => true,
                    other => return Err(format!("MTU {other}: 8 (classic) or 64 (FD)")),
                }
            }
            Self::AocsNodeId => config.cyphal.aocs_node_id = natural_u16(value)?,
            Self::NavigationNodeId => config.cyphal.navigation_node_id = natural_u16(value)?,
            Self::PortId(i) => {
                let id = natural_u16(value)?;
                *config
                    .cyphal
                    .subjects
                    .get_mut(i)
                    .ok_or("no such port".to_string())? = id;
            }
            Self::PortType(_) | Self::Setting(_) => return Err("read-only".into()),
        }
        Ok(())
    }
}

/// The register table, in `List` order.
fn table() -> Vec<(String, Field)> {
    let mut table = vec![
        ("uavcan.node.id".to_string(), Field::NodeId),
        ("uavcan.node.description".to_string(), Field::Description),
    ];
    for (i, port) in PORTS.iter().enumerate() {
        let way = match port.direction {
            Direction::Publish => "pub",
            Direction::Subscribe => "sub",
        };
        table.push((format!("uavcan.{way}.{}.id", port.name), Field::PortId(i)));
        table.push((
            format!("uavcan.{way}.{}.type", port.name),
            Field::PortType(i),
        ));
    }
    table.extend([
        ("uavcan.can.iface".to_string(), Field::CanIface),
        ("uavcan.can.mtu".to_string(), Field::CanMtu),
        ("fsw.cyphal.aocs_node_id".to_string(), Field::AocsNodeId),
        (
            "fsw.cyphal.navigation_node_id".to_string(),
            Field::NavigationNodeId,
        ),
        (
            "fsw.training.backend".to_string(),
            Field::Setting(|c| RegValue::string(&c.training.backend)),
        ),
        (
            "fsw.training.variant".to_string(),
            Field::Setting(|c| RegValue::string(&c.training.variant)),
        ),
        (
            "fsw.training.passes_per_round".to_string(),
            Field::Setting(|c| RegValue::natural32(c.training.passes_per_round)),
        ),
        (
            "fsw.sync.max_wait_ms".to_string(),
            Field::Setting(|c| RegValue::natural64(c.sync.max_wait_ms)),
        ),
        (
            "fsw.checkpoint.period_s".to_string(),
            Field::Setting(|c| RegValue::natural64(c.checkpoint.period_s)),
        ),
    ]);
    table
}

/// The answer to one Access request.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AccessOutcome {
    pub value: RegValue,
    pub mutable: bool,
    pub persistent: bool,
}

/// The register server's state.
#[derive(Debug)]
pub struct Registers {
    table: Vec<(String, Field)>,
    /// The configuration of the next start: the running one plus accepted writes.
    next_start: ComponentConfig,
    file: Option<PathBuf>,
    pub writes_accepted: u64,
    pub writes_refused: u64,
    /// Names asked for that are not registers.
    pub unknown_names: u64,
}

impl Registers {
    pub fn new(config: &ComponentConfig) -> Self {
        let file = &config.cyphal.register_file;
        Self {
            table: table(),
            next_start: config.clone(),
            file: (!file.as_os_str().is_empty()).then(|| file.clone()),
            writes_accepted: 0,
            writes_refused: 0,
            unknown_names: 0,
        }
    }

    /// The name at `index` for `List`, `None` past the last.
    pub(crate) fn name_at(&self, index: u16) -> Option<&str> {
        self.table.get(usize::from(index)).map(|(n, _)| n.as_str())
    }

    /// The configuration the component will start with next.
    pub fn next_start(&self) -> &ComponentConfig {
        &self.next_start
    }

    /// `uavcan.register.Access`: reads when `value` is empty, else tries to write; `None`
    /// for a name that is not a register.
    pub fn access(&mut self, name: &[u8], value: &Value<'_>) -> Option<AccessOutcome> {
        let Some(field) = self
            .table
            .iter()
            .find(|(n, _)| n.as_bytes() == name)
            .map(|(_, f)| *f)
        else {
            self.unknown_names += 1;
            return None;
        };
        let mutable = self.file.is_some() && field.mutable();
        if value.kind != ValueKind::Empty {
            match self.write(field, value) {
                Ok(()) => self.writes_accepted += 1,
                Err(why) => {
                    self.writes_refused += 1;
                    eprintln!(
                        "fsw-component: register {} not written: {why}",
                        String::from_utf8_lossy(name)
                    );
                }
            }
        }
        Some(AccessOutcome {
            value: field.get(&self.next_start),
            mutable,
            persistent: true,
        })
    }

    fn write(&mut self, field: Field, value: &Value<'_>) -> Result<(), String> {
        let file = self
            .file
            .clone()
            .ok_or("no [cyphal] register_file: registers are read-only")?;
        let mut next = self.next_start.clone();
        field.set(&mut next, value)?;
        next.validate().map_err(|e| e.to_string())?;
        write_register_file(&file, &self.table, &next)
            .map_err(|e| format!("{}: {e}", file.display()))?;
        self.next_start = next;
        Ok(())
    }
}

fn to_toml(value: &RegValue) -> Option<toml::Value> {
    match value.as_value().as_natural() {
        Some(n) => i64::try_from(n).ok().map(toml::Value::Integer),
        None => value.as_str().map(|s| toml::Value::String(s.to_owned())),
    }
}

/// Writes every mutable register of `config` (temporary file, then rename).
fn write_register_file(
    path: &Path,
    table: &[(String, Field)],
    config: &ComponentConfig,
) -> std::io::Result<()> {
    let mut values = toml::map::Map::new();
    for (name, field) in table.iter().filter(|(_, f)| f.mutable()) {
        if let Some(v) = to_toml(&field.get(config)) {
            values.insert(name.clone(), v);
        }
    }
    let body = toml::to_string(&values).map_err(std::io::Error::other)?;
    let text = format!(
        "# Cyphal registers written over the bus (uavcan.register.Access); read at start,\n\
         # they override component.toml. Written by fsw-component: edits are kept.\n{body}"
    );
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let temporary = path.with_extension("tmp");
    std::fs::write(&temporary, text)?;
    std::fs::rename(&temporary, path)
}

/// Applies `[cyphal] register_file` over `config` (nothing when unset or not yet written).
pub(crate) fn apply_register_file(config: &mut ComponentConfig) -> Result<(), ConfigError> {
    let path = config.cyphal.register_file.clone();
    if path.as_os_str().is_empty() || !path.exists() {
        return Ok(());
    }
    let text = std::fs::read_to_string(&path).map_err(|error| ConfigError::Read {
        path: path.clone(),
        error,
    })?;
    let parse_error = |message: String| ConfigError::Parse {
        path: path.clone(),
        message,
    };
    let values: toml::map::Map<String, toml::Value> =
        toml::from_str(&text).map_err(|e| parse_error(e.to_string()))?;
    let table = table();
    for (name, value) in &values {
        let field = table
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, f)| *f)
            .ok_or_else(|| parse_error(format!("{name:?} is not a register")))?;
        if !field.mutable() {
            return Err(parse_error(format!("register {name:?} is read-only")));
        }
        let owned = match value {
            toml::Value::Integer(n) => u64::try_from(*n)
                .map(RegValue::natural64)
                .map_err(|_| parse_error(format!("{name:?}: {n} is negative")))?,
            toml::Value::String(s) => RegValue::string(s),
            other => {
                return Err(parse_error(format!(
                    "{name:?}: want an integer or a string, got {}",
                    other.type_str()
                )))
            }
        };
        field
            .set(config, &owned.as_value())
            .map_err(|why| parse_error(format!("{name:?}: {why}")))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names() -> Vec<String> {
        let r = Registers::new(&ComponentConfig::default());
        (0..)
            .map_while(|i| r.name_at(i).map(str::to_owned))
            .collect()
    }

    #[test]
    fn every_port_has_id_and_type_registers() {
        let names = names();
        for expected in [
            "uavcan.node.id",
            "uavcan.node.description",
            "uavcan.sub.sun_vector.id",
            "uavcan.sub.target_pose.type",
            "uavcan.sub.camera_frame.id",
            "uavcan.sub.command.id",
            "uavcan.pub.command_ack.id",
            "uavcan.pub.health_status.id",
            "uavcan.pub.event.type",
            "uavcan.can.iface",
            "uavcan.can.mtu",
        ] {
            assert!(names.iter().any(|n| n == expected), "{expected}");
        }
        assert!(names.iter().all(|n| n.len() <= 255));
    }

    #[test]
    fn reads_show_the_configuration() {
        let mut config = ComponentConfig::default();
        config.node.description = "test bench".into();
        let mut r = Registers::new(&config);
        let read = |r: &mut Registers, name: &str| r.access(name.as_bytes(), &Value::EMPTY);
        let id = read(&mut r, "uavcan.node.id").unwrap();
        assert_eq!(id.value, RegValue::natural16(42));
        assert!(!id.mutable, "no register file: read-only");
        assert!(id.persistent);
        assert_eq!(
            read(&mut r, "uavcan.node.description").unwrap().value,
            RegValue::string("test bench")
        );
        assert_eq!(
            read(&mut r, "uavcan.sub.sun_vector.type").unwrap().value,
            RegValue::string("gsplat.SunVector.1.1")
        );
        assert_eq!(
            read(&mut r, "uavcan.can.mtu").unwrap().value,
            RegValue::natural16(64)
        );
        assert_eq!(read(&mut r, "no.such.register"), None);
        assert_eq!(r.unknown_names, 1);
        // A write without a register file is refused: the unchanged value comes back.
        let v = RegValue::natural16(7);
        assert_eq!(
            r.access(b"uavcan.node.id", &v.as_value()).unwrap().value,
            RegValue::natural16(42)
        );
        assert_eq!(r.writes_refused, 1);
    }

    fn scratch(test: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("fsw-registers-{}-{test}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn writes_persist_take_effect_at_the_next_start_and_bad_ones_are_refused() {
        let dir = scratch("persist");
        let file = dir.join("registers.toml");
        let toml = format!(
            "[cyphal]\nregister_file = {:?}\n",
            file.display().to_string()
        );
        let config = ComponentConfig::from_toml_str(&toml, Path::new("t.toml")).unwrap();
        let mut r = Registers::new(&config);
        let write = |r: &mut Registers, name: &str, v: RegValue| {
            r.access(name.as_bytes(), &v.as_value()).unwrap()
        };
        let out = write(
            &mut r,
            "uavcan.pub.health_status.id",
            RegValue::natural16(500),
        );
        assert_eq!(out.value, RegValue::natural16(500));
        assert!(out.mutable && out.persistent);
        // Any natural width is taken; the answer has the register's own type.
        let out = write(&mut r, "uavcan.node.id", RegValue::natural32(43));
        assert_eq!(out.value, RegValue::natural16(43));
        write(&mut r, "uavcan.node.description", RegValue::string("moved"));
        assert_eq!(r.writes_accepted, 3);
        // Refused, unchanged value back: a duplicate port, a bad MTU, a wrong type, a node-ID
        // out of range, a read-only register.
        for (name, value, unchanged) in [
            (
                "uavcan.sub.command.id",
                RegValue::natural16(500),
                RegValue::natural16(300),
            ),
            (
                "uavcan.can.mtu",
                RegValue::natural16(12),
                RegValue::natural16(64),
            ),
            (
                "uavcan.node.id",
                RegValue::string("7"),
                RegValue::natural16(43),
            ),
            (
                "uavcan.node.id",
                RegValue::natural16(200),
                RegValue::natural16(43),
            ),
            (
                "uavcan.sub.command.type",
                RegValue::string("x"),
                RegValue::string("gsplat.Command.1.1"),
            ),
        ] {
            assert_eq!(write(&mut r, name, value).value, unchanged, "{name}");
        }
        assert_eq!(r.writes_refused, 5);
        // The running configuration is untouched; the next start reads the file.
        assert_eq!(config.cyphal.subjects.health_status, 400);
        let restarted = ComponentConfig::from_toml_str(&toml, Path::new("t.toml")).unwrap();
        assert_eq!(restarted.cyphal.subjects.health_status, 500);
        assert_eq!(restarted.node.node_id, 43);
        assert_eq!(restarted.node.description, "moved");
        assert_eq!(&restarted, r.next_start());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn bad_register_files_stop_the_start_with_the_file_name() {
        let dir = scratch("bad");
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("registers.toml");
        let toml = format!(
            "[cyphal]\nregister_file = {:?}\n",
            file.display().to_string()
        );
        for (content, expected) in [
            ("\"no.such\" = 1\n", "not a register"),
            ("\"uavcan.pub.event.type\" = \"x\"\n", "read-only"),
            ("\"uavcan.node.id\" = -1\n", "negative"),
            ("\"uavcan.node.id\" = 1.5\n", "want an integer"),
            (
                "\"uavcan.sub.sun_vector.id\" = 9000\n",
                "cyphal.subjects.sun_vector",
            ),
        ] {
            std::fs::write(&file, content).unwrap();
            let message = ComponentConfig::from_toml_str(&toml, Path::new("t.toml"))
                .unwrap_err()
                .to_string();
            assert!(message.contains(expected), "{content}: {message}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
