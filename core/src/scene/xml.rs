//! Mitsuba 3 XML -> a tree of plugin objects with typed, position-tagged properties.
//!
//! The tree is an arena: every `<shape>`, `<bsdf>`, ... element becomes an [`Obj`]; `<ref>`s
//! point at the arena index of the object they name, so a BSDF shared by several shapes is one
//! object. Every property and nested object remembers whether the scene builder consumed it;
//! whatever is left over afterwards is reported as unsupported (nothing is silently ignored).

use std::cell::Cell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3, Vec4};

use super::SceneError;

/// 1-based line and column of an element in the scene file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Pos {
    pub line: u32,
    pub col: u32,
}

#[derive(Clone, Debug)]
pub enum Value {
    Integer(i64),
    Float(f64),
    Str(String),
    Boolean(bool),
    Rgb(Vec3),
    Point(Vec3),
    Vector(Vec3),
    Transform(Mat4),
}

impl Value {
    fn type_name(&self) -> &'static str {
        match self {
            Value::Integer(_) => "integer",
            Value::Float(_) => "float",
            Value::Str(_) => "string",
            Value::Boolean(_) => "boolean",
            Value::Rgb(_) => "rgb",
            Value::Point(_) => "point",
            Value::Vector(_) => "vector",
            Value::Transform(_) => "transform",
        }
    }
}

#[derive(Debug)]
pub struct Prop {
    pub name: String,
    pub value: Value,
    pub pos: Pos,
    used: Cell<bool>,
}

impl Prop {
    /// A property set by a program rather than read from the file (at the object's position).
    pub fn new(name: &str, value: Value, pos: Pos) -> Prop {
        Prop { name: name.to_string(), value, pos, used: Cell::new(false) }
    }
}

/// A nested object: `<bsdf .../>` inside a shape, or a `<ref id=.../>`.
#[derive(Debug)]
pub struct Child {
    pub name: Option<String>,
    pub obj: usize,
    pub pos: Pos,
    used: Cell<bool>,
}

/// One plugin instance: `<tag type="plugin" id="...">`.
#[derive(Debug)]
pub struct Obj {
    pub tag: String,
    pub plugin: String,
    pub id: Option<String>,
    pub pos: Pos,
    pub props: Vec<Prop>,
    pub children: Vec<Child>,
}

/// A parsed scene file.
#[derive(Debug)]
pub struct Doc {
    pub file: PathBuf,
    pub dir: PathBuf,
    pub objs: Vec<Obj>,
    pub root: usize,
}

/// The largest coordinate a scene may hold, anywhere (points, transform entries, shapes in
/// world space): f32 geometry squares distances, and past this their sums lose all precision
/// or overflow.
pub const MAX_COORD: f32 = 1e15;

/// How deep objects may nest (`<bsdf>` in `<bsdf>` in ...): real scenes use a handful; the
/// parser and builder recurse, and a thread's stack is finite.
pub const MAX_NESTING: usize = 64;

const OBJECT_TAGS: &[&str] =
    &["shape", "bsdf", "texture", "emitter", "sensor", "film", "rfilter", "sampler", "integrator"];

impl Doc {
    /// Calls `f` on every object with this tag and plugin (`furnace report`'s ablations edit
    /// a parsed scene this way before it is built).
    pub fn edit(&mut self, tag: &str, plugin: &str, mut f: impl FnMut(&mut Obj)) {
        for o in self.objs.iter_mut().filter(|o| o.tag == tag && o.plugin == plugin) {
            f(o);
        }
    }

    pub fn err(&self, pos: Pos, message: impl Into<String>) -> SceneError {
        SceneError::at(&self.file, pos, message)
    }

    pub fn obj(&self, i: usize) -> &Obj {
        &self.objs[i]
    }

    /// "bsdf 'diffuse'" (with its id when it has one), for messages.
    pub fn describe(&self, i: usize) -> String {
        let o = &self.objs[i];
        match &o.id {
            Some(id) => format!("{} '{}' (id '{}')", o.tag, o.plugin, id),
            None => format!("{} '{}'", o.tag, o.plugin),
        }
    }

    /// Reports the first property or nested object of `root` (and, depth first, of the objects
    /// it consumed) that the builder did not use. Each object is looked at once, without
    /// recursion: `<ref>`s may name one object many times and chain deeply.
    pub fn check_all_used(&self, root: usize) -> Result<(), SceneError> {
        let mut seen = vec![false; self.objs.len()];
        // (object, and the parent and child entry it was reached by)
        let mut stack: Vec<(usize, Option<(usize, usize)>)> = vec![(root, None)];
        while let Some((i, via)) = stack.pop() {
            if let Some((parent, k)) = via {
                let c = &self.objs[parent].children[k];
                if !c.used.get() {
                    let what = match &c.name {
                        Some(n) => format!("{} named '{}'", self.describe(c.obj), n),
                        None => self.describe(c.obj),
                    };
                    let msg = format!("unsupported nested {} inside {}", what, self.describe(parent));
                    return Err(self.err(c.pos, msg));
                }
            }
            if std::mem::replace(&mut seen[i], true) {
                continue;
            }
            let o = &self.objs[i];
            if let Some(p) = o.props.iter().find(|p| !p.used.get()) {
                let what = format!("'{}' ({}) for {}", p.name, p.value.type_name(), self.describe(i));
                return Err(self.err(p.pos, format!("unsupported parameter {what}")));
            }
            stack.extend((0..o.children.len()).rev().map(|k| (o.children[k].obj, Some((i, k)))));
        }
        Ok(())
    }

    fn prop(&self, i: usize, name: &str) -> Option<&Prop> {
        let p = self.objs[i].props.iter().find(|p| p.name == name)?;
        p.used.set(true);
        Some(p)
    }

    fn type_err(&self, i: usize, p: &Prop, expected: &str) -> SceneError {
        self.err(
            p.pos,
            format!(
                "parameter '{}' of {} must be {}, found {}",
                p.name,
                self.describe(i),
                expected,
                p.value.type_name()
            ),
        )
    }

    pub fn has(&self, i: usize, name: &str) -> bool {
        self.objs[i].props.iter().any(|p| p.name == name)
    }

    pub fn pos_of(&self, i: usize, name: &str) -> Pos {
        self.objs[i].props.iter().find(|p| p.name == name).map(|p| p.pos).unwrap_or(self.objs[i].pos)
    }

    pub fn float(&self, i: usize, name: &str) -> Result<Option<f32>, SceneError> {
        match self.prop(i, name) {
            None => Ok(None),
            Some(p) => match p.value {
                Value::Float(v) => Ok(Some(v as f32)),
                Value::Integer(v) => Ok(Some(v as f32)),
                _ => Err(self.type_err(i, p, "a float")),
            },
        }
    }

    pub fn float_or(&self, i: usize, name: &str, default: f32) -> Result<f32, SceneError> {
        Ok(self.float(i, name)?.unwrap_or(default))
    }

    pub fn int(&self, i: usize, name: &str) -> Result<Option<i64>, SceneError> {
        match self.prop(i, name) {
            None => Ok(None),
            Some(p) => match p.value {
                Value::Integer(v) => Ok(Some(v)),
                _ => Err(self.type_err(i, p, "an integer")),
            },
        }
    }

    pub fn int_or(&self, i: usize, name: &str, default: i64) -> Result<i64, SceneError> {
        Ok(self.int(i, name)?.unwrap_or(default))
    }

    pub fn boolean_or(&self, i: usize, name: &str, default: bool) -> Result<bool, SceneError> {
        match self.prop(i, name) {
            None => Ok(default),
            Some(p) => match p.value {
                Value::Boolean(v) => Ok(v),
                _ => Err(self.type_err(i, p, "a boolean")),
            },
        }
    }

    pub fn string(&self, i: usize, name: &str) -> Result<Option<String>, SceneError> {
        match self.prop(i, name) {
            None => Ok(None),
            Some(p) => match &p.value {
                Value::Str(v) => Ok(Some(v.clone())),
                _ => Err(self.type_err(i, p, "a string")),
            },
        }
    }

    /// A colour: `<rgb>` or a single `<float>` (grey).
    pub fn rgb(&self, i: usize, name: &str) -> Result<Option<Vec3>, SceneError> {
        match self.prop(i, name) {
            None => Ok(None),
            Some(p) => match p.value {
                Value::Rgb(v) => Ok(Some(v)),
                Value::Float(v) => Ok(Some(Vec3::splat(v as f32))),
                Value::Integer(v) => Ok(Some(Vec3::splat(v as f32))),
                _ => Err(self.type_err(i, p, "an rgb colour or a float")),
            },
        }
    }

    pub fn point(&self, i: usize, name: &str) -> Result<Option<Vec3>, SceneError> {
        match self.prop(i, name) {
            None => Ok(None),
            Some(p) => match p.value {
                Value::Point(v) | Value::Vector(v) => Ok(Some(v)),
                _ => Err(self.type_err(i, p, "a point")),
            },
        }
    }

    pub fn transform(&self, i: usize, name: &str) -> Result<Option<Mat4>, SceneError> {
        match self.prop(i, name) {
            None => Ok(None),
            Some(p) => match p.value {
                Value::Transform(m) => Ok(Some(m)),
                _ => Err(self.type_err(i, p, "a transform")),
            },
        }
    }

    /// Nested objects of `i` with the given tag, marked as used.
    pub fn children(&self, i: usize, tag: &str) -> Vec<(Option<String>, usize, Pos)> {
        self.objs[i]
            .children
            .iter()
            .filter(|c| self.objs[c.obj].tag == tag)
            .map(|c| {
                c.used.set(true);
                (c.name.clone(), c.obj, c.pos)
            })
            .collect()
    }

    /// The nested object of `i` passed under parameter `name` (`<texture name="reflectance">`
    /// or `<ref name="reflectance" id="..."/>`), marked as used.
    pub fn named_child(&self, i: usize, name: &str) -> Option<usize> {
        let c = self.objs[i].children.iter().find(|c| c.name.as_deref() == Some(name))?;
        c.used.set(true);
        Some(c.obj)
    }

    /// Whether `i` has a nested object passed as parameter `name` (does not mark it used).
    pub fn named_child_exists(&self, i: usize, name: &str) -> bool {
        self.objs[i].children.iter().any(|c| c.name.as_deref() == Some(name))
    }

    /// Resolves an asset path relative to the scene's folder; refuses paths that leave it.
    /// The path returned goes through the folder as it was given (with its canonical path
    /// inside it): a folder reached through a descriptor (`/proc/self/fd/N`, a worker's
    /// cache) stays that folder, whatever is renamed around it after the check.
    pub fn resolve_path(&self, pos: Pos, rel: &str) -> Result<PathBuf, SceneError> {
        let joined = self.dir.join(rel);
        let canon = joined
            .canonicalize()
            .map_err(|e| self.err(pos, format!("cannot open file '{}': {e}", joined.display())))?;
        let base = self
            .dir
            .canonicalize()
            .map_err(|e| self.err(pos, format!("cannot open scene folder '{}': {e}", self.dir.display())))?;
        let Ok(inside) = canon.strip_prefix(&base) else {
            return Err(self.err(
                pos,
                format!(
                    "file '{rel}' lies outside the scene's folder '{}'; scene assets must live beside the scene",
                    base.display()
                ),
            ));
        };
        Ok(self.dir.join(inside))
    }
}

/// Parses a scene file. `defines` are `-D name=value` overrides of `<default>`s.
pub fn parse_file(path: &Path, defines: &[(String, String)]) -> Result<Doc, SceneError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| SceneError::file(path, format!("cannot read scene file: {e}")))?;
    parse_str(&text, path, defines)
}

/// Parses scene XML text; `path` names the file in messages and anchors relative asset paths.
pub fn parse_str(text: &str, path: &Path, defines: &[(String, String)]) -> Result<Doc, SceneError> {
    let xml = roxmltree::Document::parse(text).map_err(|e| {
        let p = e.pos();
        SceneError::at(path, Pos { line: p.row, col: p.col }, format!("malformed XML: {e}"))
    })?;
    let dir = path
        .parent()
        .map(|p| if p.as_os_str().is_empty() { Path::new(".") } else { p })
        .unwrap_or(Path::new("."))
        .to_path_buf();
    let mut parser = Parser {
        lines: LineIndex::new(text),
        file: path.to_path_buf(),
        params: HashMap::new(),
        ids: HashMap::new(),
        objs: Vec::new(),
    };
    let root = xml.root_element();
    if root.tag_name().name() != "scene" {
        return Err(
            parser.err(root, format!("the root element must be <scene>, found <{}>", root.tag_name().name()))
        );
    }
    parser.check_attrs(root, &["version"])?;
    match root.attribute("version") {
        None => return Err(parser.err(root, "<scene> needs a version attribute, e.g. version=\"3.0.0\"")),
        Some(v) => {
            let parts: Vec<&str> = v.split('.').collect();
            let numeric = |p: &&str| !p.is_empty() && p.len() <= 9 && p.bytes().all(|b| b.is_ascii_digit());
            if parts.len() != 3 || !parts.iter().all(numeric) {
                return Err(parser.err(
                    root,
                    format!("invalid version number \"{v}\": expected major.minor.patch, e.g. \"3.0.0\""),
                ));
            }
        }
    }
    // <default>s first, so that `$name` works anywhere; -D overrides them.
    for c in root.children().filter(|c| c.is_element()) {
        if c.tag_name().name() == "default" {
            parser.check_attrs(c, &["name", "value"])?;
            let name = parser.required_attr(c, "name")?;
            let value = parser.required_attr(c, "value")?;
            parser.params.insert(name, value);
        }
    }
    for (k, v) in defines {
        parser.params.insert(k.clone(), v.clone());
    }
    let root_idx = parser.parse_object(root, "scene".into(), String::new(), 0)?;
    Ok(Doc { file: path.to_path_buf(), dir, objs: parser.objs, root: root_idx })
}

/// Line and column of byte offsets in a text, each found in O(log n) (roxmltree's
/// `text_pos_at` scans from the start: quadratic over a large scene's elements). Columns count
/// characters from 1, as roxmltree's do.
struct LineIndex<'i> {
    text: &'i [u8],
    /// Byte offset where each line starts.
    starts: Vec<usize>,
    /// Characters before byte `k * CHUNK`.
    chars: Vec<usize>,
}

impl<'i> LineIndex<'i> {
    const CHUNK: usize = 1024;

    fn new(text: &'i str) -> Self {
        let text = text.as_bytes();
        let starts = std::iter::once(0).chain(newline_ends(text)).collect();
        let mut chars = vec![0];
        for c in text.chunks(Self::CHUNK) {
            chars.push(chars[chars.len() - 1] + count_chars(c));
        }
        LineIndex { text, starts, chars }
    }

    /// Characters before byte `at`.
    fn chars_before(&self, at: usize) -> usize {
        let k = at / Self::CHUNK;
        self.chars[k] + count_chars(&self.text[k * Self::CHUNK..at])
    }

    fn pos(&self, at: usize) -> Pos {
        let at = at.min(self.text.len());
        let line = self.starts.partition_point(|&s| s <= at);
        let start = self.starts[line - 1];
        Pos { line: line as u32, col: (self.chars_before(at) - self.chars_before(start) + 1) as u32 }
    }
}

/// Offsets just after each newline.
fn newline_ends(text: &[u8]) -> impl Iterator<Item = usize> + '_ {
    text.iter().enumerate().filter(|(_, &b)| b == b'\n').map(|(i, _)| i + 1)
}

/// UTF-8 characters in `bytes` (bytes that do not continue a character).
fn count_chars(bytes: &[u8]) -> usize {
    bytes.iter().filter(|&&b| b & 0xC0 != 0x80).count()
}

struct Parser<'i> {
    lines: LineIndex<'i>,
    file: PathBuf,
    params: HashMap<String, String>,
    ids: HashMap<String, usize>,
    objs: Vec<Obj>,
}

impl Parser<'_> {
    fn pos(&self, node: roxmltree::Node) -> Pos {
        self.lines.pos(node.range().start)
    }

    fn err(&self, node: roxmltree::Node, message: impl Into<String>) -> SceneError {
        SceneError::at(&self.file, self.pos(node), message)
    }

    /// Attribute value after `$name` substitution.
    fn attr(&self, node: roxmltree::Node, name: &str) -> Result<Option<String>, SceneError> {
        let Some(raw) = node.attribute(name) else {
            return Ok(None);
        };
        if !raw.contains('$') {
            return Ok(Some(raw.to_string()));
        }
        let mut out = String::with_capacity(raw.len());
        let mut rest = raw;
        while let Some(k) = rest.find('$') {
            out.push_str(&rest[..k]);
            let after = &rest[k + 1..];
            let len = after
                .char_indices()
                .find(|(_, c)| !(c.is_ascii_alphanumeric() || *c == '_'))
                .map(|(i, _)| i)
                .unwrap_or(after.len());
            let key = &after[..len];
            if key.is_empty() {
                return Err(self.err(node, format!("'$' without a parameter name in \"{raw}\"")));
            }
            match self.params.get(key) {
                Some(v) => out.push_str(v),
                None => {
                    return Err(self.err(
                        node,
                        format!(
                            "parameter '${key}' is not defined: add <default name=\"{key}\" value=\"...\"/> or pass -D {key}=..."
                        ),
                    ))
                }
            }
            rest = &after[len..];
        }
        out.push_str(rest);
        Ok(Some(out))
    }

    /// Refuses attributes an element does not take (as Mitsuba does): a misspelt one would
    /// otherwise be ignored without a word.
    fn check_attrs(&self, node: roxmltree::Node, allowed: &[&str]) -> Result<(), SceneError> {
        for a in node.attributes() {
            if a.namespace().is_none() && !allowed.contains(&a.name()) {
                return Err(self.err(
                    node,
                    format!(
                        "unexpected attribute \"{}\" in element <{}> (it takes: {})",
                        a.name(),
                        node.tag_name().name(),
                        allowed.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }

    fn required_attr(&self, node: roxmltree::Node, name: &str) -> Result<String, SceneError> {
        self.attr(node, name)?.ok_or_else(|| {
            self.err(node, format!("<{}> needs a '{}' attribute", node.tag_name().name(), name))
        })
    }

    fn parse_object(
        &mut self,
        node: roxmltree::Node,
        tag: String,
        plugin: String,
        depth: usize,
    ) -> Result<usize, SceneError> {
        if depth > MAX_NESTING {
            return Err(self.err(node, format!("objects nest deeper than {MAX_NESTING} levels")));
        }
        let mut obj = Obj {
            tag,
            plugin,
            id: self.attr(node, "id")?,
            pos: self.pos(node),
            props: Vec::new(),
            children: Vec::new(),
        };
        for c in node.children().filter(|c| c.is_element()) {
            let ctag = c.tag_name().name();
            match ctag {
                "default" if obj.tag == "scene" => {}
                "integer" | "float" | "string" | "boolean" | "rgb" => {
                    self.check_attrs(c, &["name", "value"])?;
                    let name = self.required_attr(c, "name")?;
                    let value = self.parse_value(c, ctag)?;
                    self.push_prop(&mut obj, c, name, value)?;
                }
                "point" | "vector" => {
                    self.check_attrs(c, &["name", "value", "x", "y", "z"])?;
                    let name = self.required_attr(c, "name")?;
                    let value = self.parse_value(c, ctag)?;
                    self.push_prop(&mut obj, c, name, value)?;
                }
                "transform" => {
                    self.check_attrs(c, &["name"])?;
                    let name = self.required_attr(c, "name")?;
                    let m = self.parse_transform(c)?;
                    self.push_prop(&mut obj, c, name, Value::Transform(m))?;
                }
                "ref" => {
                    self.check_attrs(c, &["id", "name"])?;
                    let id = self.required_attr(c, "id")?;
                    let target = *self.ids.get(&id).ok_or_else(|| {
                        self.err(c, format!("<ref id=\"{id}\"/> names no object defined before it"))
                    })?;
                    obj.children.push(Child {
                        name: self.attr(c, "name")?,
                        obj: target,
                        pos: self.pos(c),
                        used: Cell::new(false),
                    });
                }
                t if OBJECT_TAGS.contains(&t) => {
                    self.check_attrs(c, &["type", "id", "name"])?;
                    let plugin = self.required_attr(c, "type")?;
                    let name = self.attr(c, "name")?;
                    let idx = self.parse_object(c, t.to_string(), plugin, depth + 1)?;
                    obj.children.push(Child { name, obj: idx, pos: self.pos(c), used: Cell::new(false) });
                }
                other => {
                    return Err(self.err(c, format!("unsupported element <{other}> inside <{}>", obj.tag)))
                }
            }
        }
        let id = obj.id.clone();
        let idx = self.objs.len();
        self.objs.push(obj);
        if let Some(id) = id {
            if self.ids.insert(id.clone(), idx).is_some() {
                return Err(self.err(node, format!("id '{id}' is defined twice")));
            }
        }
        Ok(idx)
    }

    fn push_prop(
        &self,
        obj: &mut Obj,
        node: roxmltree::Node,
        name: String,
        value: Value,
    ) -> Result<(), SceneError> {
        if obj.props.iter().any(|p| p.name == name) {
            return Err(self.err(node, format!("parameter '{name}' is given twice")));
        }
        obj.props.push(Prop { name, value, pos: self.pos(node), used: Cell::new(false) });
        Ok(())
    }

    /// A number that a 32-bit float holds: finite, and at most f32::MAX in magnitude.
    fn number(&self, node: roxmltree::Node, s: &str) -> Result<f64, SceneError> {
        let v = s
            .trim()
            .parse::<f64>()
            .map_err(|_| self.err(node, format!("expected a number, found \"{s}\"")))?;
        if !v.is_finite() || v.abs() > f32::MAX as f64 {
            return Err(self.err(
                node,
                format!("expected a finite number within the range of a 32-bit float, found \"{s}\""),
            ));
        }
        Ok(v)
    }

    /// A position or direction: each coordinate within +-[`MAX_COORD`].
    fn coords(&self, node: roxmltree::Node, v: Vec3) -> Result<Vec3, SceneError> {
        if v.abs().max_element() > MAX_COORD {
            return Err(self.err(
                node,
                format!("coordinates ({:e}, {:e}, {:e}) lie beyond +-{MAX_COORD:e}, more than 32-bit float geometry can hold", v.x, v.y, v.z),
            ));
        }
        Ok(v)
    }

    fn numbers(&self, node: roxmltree::Node, s: &str) -> Result<Vec<f64>, SceneError> {
        s.split(|c: char| c == ',' || c.is_whitespace())
            .filter(|t| !t.is_empty())
            .map(|t| self.number(node, t))
            .collect()
    }

    /// A 3-vector from `value="x, y, z"` (or one number, when `splat`) or x/y/z attributes.
    fn vec3(&self, node: roxmltree::Node, default: f32, splat: bool) -> Result<Vec3, SceneError> {
        if let Some(v) = self.attr(node, "value")? {
            let n = self.numbers(node, &v)?;
            return match n.len() {
                3 => Ok(Vec3::new(n[0] as f32, n[1] as f32, n[2] as f32)),
                1 if splat => Ok(Vec3::splat(n[0] as f32)),
                _ => Err(self.err(
                    node,
                    format!("expected {} numbers, found \"{v}\"", if splat { "1 or 3" } else { "3" }),
                )),
            };
        }
        let mut out = Vec3::splat(default);
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            if let Some(s) = self.attr(node, axis)? {
                out[k] = self.number(node, &s)? as f32;
            }
        }
        Ok(out)
    }

    fn parse_value(&self, node: roxmltree::Node, tag: &str) -> Result<Value, SceneError> {
        Ok(match tag {
            "point" | "vector" => {
                let v = self.coords(node, self.vec3(node, 0.0, false)?)?;
                if tag == "point" {
                    Value::Point(v)
                } else {
                    Value::Vector(v)
                }
            }
            "rgb" => {
                let v = self.required_attr(node, "value")?;
                let n = self.numbers(node, &v)?;
                match n.len() {
                    1 => Value::Rgb(Vec3::splat(n[0] as f32)),
                    3 => Value::Rgb(Vec3::new(n[0] as f32, n[1] as f32, n[2] as f32)),
                    _ => return Err(self.err(node, format!("<rgb> expects 1 or 3 numbers, found \"{v}\""))),
                }
            }
            _ => {
                let v = self.required_attr(node, "value")?;
                match tag {
                    "integer" => Value::Integer(
                        v.trim()
                            .parse::<i64>()
                            .map_err(|_| self.err(node, format!("expected an integer, found \"{v}\"")))?,
                    ),
                    "float" => Value::Float(self.number(node, &v)?),
                    "boolean" => match v.trim().to_ascii_lowercase().as_str() {
                        "true" => Value::Boolean(true),
                        "false" => Value::Boolean(false),
                        _ => return Err(self.err(node, format!("expected true or false, found \"{v}\""))),
                    },
                    _ => Value::Str(v),
                }
            }
        })
    }

    /// `<transform>`: operations compose in document order, the first child innermost.
    fn parse_transform(&self, node: roxmltree::Node) -> Result<Mat4, SceneError> {
        let mut m = Mat4::IDENTITY;
        for c in node.children().filter(|c| c.is_element()) {
            let allowed: &[&str] = match c.tag_name().name() {
                "translate" | "scale" => &["value", "x", "y", "z"],
                "rotate" => &["value", "x", "y", "z", "angle"],
                "matrix" => &["value"],
                "lookat" => &["origin", "target", "up"],
                _ => &[],
            };
            self.check_attrs(c, allowed)?;
            let op = match c.tag_name().name() {
                "translate" => Mat4::from_translation(self.coords(c, self.vec3(c, 0.0, false)?)?),
                "scale" => Mat4::from_scale(self.coords(c, self.vec3(c, 1.0, true)?)?),
                "rotate" => {
                    let axis = self.vec3(c, 0.0, false)?;
                    let angle = self.number(c, &self.required_attr(c, "angle")?)? as f32;
                    if axis.length_squared() == 0.0 {
                        return Err(self.err(c, "<rotate> needs a non-zero axis (x, y, z)"));
                    }
                    Mat4::from_axis_angle(axis.normalize(), angle.to_radians())
                }
                "matrix" => {
                    let v = self.required_attr(c, "value")?;
                    let n = self.numbers(c, &v)?;
                    let f: Vec<f32> = n.iter().map(|&x| x as f32).collect();
                    match f.len() {
                        16 if f[12..] != [0.0, 0.0, 0.0, 1.0] => {
                            let row = format!("{} {} {} {}", f[12], f[13], f[14], f[15]);
                            let msg =
                                format!("<matrix> must be affine: its last row must be 0 0 0 1, found {row}");
                            return Err(self.err(c, msg));
                        }
                        // Row-major in the file; glam is column-major.
                        16 => Mat4::from_cols_array(&[
                            f[0], f[4], f[8], f[12], f[1], f[5], f[9], f[13], f[2], f[6], f[10], f[14], f[3],
                            f[7], f[11], f[15],
                        ]),
                        9 => Mat4::from_cols(
                            Vec4::new(f[0], f[3], f[6], 0.0),
                            Vec4::new(f[1], f[4], f[7], 0.0),
                            Vec4::new(f[2], f[5], f[8], 0.0),
                            Vec4::W,
                        ),
                        k => return Err(self.err(c, format!("<matrix> expects 9 or 16 numbers, found {k}"))),
                    }
                }
                "lookat" => {
                    let p = |name: &str| -> Result<Vec3, SceneError> {
                        let s = self.required_attr(c, name)?;
                        let n = self.numbers(c, &s)?;
                        if n.len() != 3 {
                            return Err(self.err(c, format!("'{name}' expects 3 numbers, found \"{s}\"")));
                        }
                        Ok(Vec3::new(n[0] as f32, n[1] as f32, n[2] as f32))
                    };
                    let origin = self.coords(c, p("origin")?)?;
                    let target = self.coords(c, p("target")?)?;
                    let dir = (target - origin).normalize_or_zero();
                    if dir == Vec3::ZERO {
                        return Err(self.err(c, "<lookat> origin and target coincide"));
                    }
                    // Without `up` (or with a zero one), Mitsuba takes the first tangent of the
                    // Duff et al. orthonormal basis around the viewing direction.
                    let mut up = if c.attribute("up").is_some() { p("up")? } else { Vec3::ZERO };
                    if up.length_squared() == 0.0 {
                        up = crate::math::Frame::from_normal(dir).s;
                    }
                    let left = up.cross(dir);
                    if left.length_squared() < 1e-12 {
                        return Err(self.err(c, "<lookat> 'up' is parallel to the viewing direction"));
                    }
                    let left = left.normalize();
                    let new_up = dir.cross(left);
                    Mat4::from_cols(left.extend(0.0), new_up.extend(0.0), dir.extend(0.0), origin.extend(1.0))
                }
                other => return Err(self.err(c, format!("unsupported transform operation <{other}>"))),
            };
            m = op * m;
            if !m.is_finite() || m.abs().to_cols_array().iter().any(|&x| x > MAX_COORD) {
                return Err(self.err(
                    c,
                    format!("the transform reaches values beyond +-{MAX_COORD:e}, more than 32-bit float geometry can hold"),
                ));
            }
        }
        let det = m.determinant();
        if !(det.abs() > 0.0) || !det.is_finite() || !m.inverse().is_finite() {
            return Err(self.err(
                node,
                format!("the transform is singular or cannot be inverted in 32-bit floats (determinant {det}): normals and inverses would be undefined"),
            ));
        }
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The index agrees with roxmltree's own (linear-time) positions on every element, across
    /// multi-byte characters, CRLF line ends, and lines longer than the index's chunks.
    #[test]
    fn line_index_agrees_with_roxmltree() {
        let mut text = String::from("<scene version=\"3.0.0\">\r\n<!-- é ü 漢字 -->\n");
        for i in 0..300 {
            let pad = "ü".repeat(i * 7 % 1500);
            text.push_str(&format!("<a n=\"{pad}\"/><b>é{i}</b>"));
            if i % 3 == 0 {
                text.push_str("\r\n");
            }
        }
        text.push_str("</scene>");
        let doc = roxmltree::Document::parse(&text).unwrap();
        let index = LineIndex::new(&text);
        let mut checked = 0;
        for node in doc.descendants() {
            let at = node.range().start;
            let want = doc.text_pos_at(at);
            assert_eq!(index.pos(at), Pos { line: want.row, col: want.col }, "at byte {at}");
            checked += 1;
        }
        assert!(checked > 600);
    }
}
