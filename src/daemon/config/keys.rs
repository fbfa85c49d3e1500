//! The keys a config file may hold, read off the `Raw*` structs' own `Deserialize`
//! implementations, which are where the file's shape is declared: the reload policy is
//! checked against them (a key added to a struct without a reload decision fails the
//! suite), and so is the list of known tables a parse error gives. A [`Tracer`] is a serde
//! deserializer that offers every field of every struct it is asked for, with a neutral
//! value for each, and writes down the dotted path of each field on the way.

use serde::de::value::{Error, StrDeserializer};
use serde::de::{self, DeserializeSeed, IntoDeserializer, Visitor};
use serde::Deserialize;
use std::cell::RefCell;

/// Every key of the file, dotted from the top (`printer.simulate.seed`), tables included
/// (`printer.simulate`). A free-form value (`folder.settings`, `folder.strength`) is one
/// key: what it holds is checked by its own type, not named by a struct.
pub(crate) fn all() -> Result<Vec<String>, Error> {
    let keys = RefCell::new(Vec::new());
    super::raw::RawConfig::deserialize(Tracer {
        prefix: "",
        keys: &keys,
    })?;
    Ok(keys.into_inner())
}

/// The top-level tables (`spool`, ..., `notify`), as a header names them.
pub(crate) fn tables() -> Result<Vec<String>, Error> {
    Ok(all()?.into_iter().filter(|k| !k.contains('.')).collect())
}

/// A value at `prefix` (the key it is the value of); see the module's comment.
#[derive(Clone, Copy)]
struct Tracer<'a> {
    prefix: &'a str,
    keys: &'a RefCell<Vec<String>>,
}

impl<'de> de::Deserializer<'de> for Tracer<'_> {
    type Error = Error;

    /// A value whose shape the type does not say (a `toml::Value`): an empty table.
    fn deserialize_any<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_map(visitor)
    }

    fn deserialize_map<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_map(de::value::MapDeserializer::new(std::iter::empty::<(
            &str,
            &str,
        )>()))
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, Error> {
        let paths: Vec<String> = fields
            .iter()
            .map(|f| match self.prefix {
                "" => f.to_string(),
                p => format!("{p}.{f}"),
            })
            .collect();
        self.keys.borrow_mut().extend(paths.iter().cloned());
        visitor.visit_map(Fields {
            fields,
            paths,
            next: 0,
            keys: self.keys,
        })
    }

    fn deserialize_option<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_some(self)
    }

    /// An array (of tables: `[[printer]]`): one element, whose keys are the array's.
    fn deserialize_seq<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_seq(Elements {
            tracer: self,
            left: 1,
        })
    }

    fn deserialize_tuple<V: Visitor<'de>>(self, len: usize, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_seq(Elements {
            tracer: self,
            left: len,
        })
    }

    /// An enumeration of words (`on_shutdown`, `slicer`): its first.
    fn deserialize_enum<V: Visitor<'de>>(
        self,
        _name: &'static str,
        variants: &'static [&'static str],
        visitor: V,
    ) -> Result<V::Value, Error> {
        let first = variants.first().copied().unwrap_or_default();
        visitor.visit_enum(first.into_deserializer())
    }

    fn deserialize_newtype_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        visitor: V,
    ) -> Result<V::Value, Error> {
        visitor.visit_newtype_struct(self)
    }

    fn deserialize_bool<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_bool(false)
    }

    /// Every integer: 0, which every integer type takes.
    fn deserialize_i64<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_u8(0)
    }

    fn deserialize_f64<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_f64(0.0)
    }

    fn deserialize_str<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_str("")
    }

    fn deserialize_unit<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_unit()
    }

    fn deserialize_ignored_any<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        visitor.visit_unit()
    }

    serde::forward_to_deserialize_any! {
        char bytes byte_buf unit_struct tuple_struct identifier
    }

    fn deserialize_i8<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_i16<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_i32<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_u8<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_u16<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_u32<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_u64<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_i64(visitor)
    }
    fn deserialize_f32<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_f64(visitor)
    }
    fn deserialize_string<V: Visitor<'de>>(self, visitor: V) -> Result<V::Value, Error> {
        self.deserialize_str(visitor)
    }
}

/// A struct's fields, each given with a traced value.
struct Fields<'a> {
    fields: &'static [&'static str],
    paths: Vec<String>,
    next: usize,
    keys: &'a RefCell<Vec<String>>,
}

impl<'de> de::MapAccess<'de> for Fields<'_> {
    type Error = Error;

    fn next_key_seed<K: DeserializeSeed<'de>>(
        &mut self,
        seed: K,
    ) -> Result<Option<K::Value>, Error> {
        let Some(field) = self.fields.get(self.next) else {
            return Ok(None);
        };
        let name: StrDeserializer<'_, Error> = field.into_deserializer();
        seed.deserialize(name).map(Some)
    }

    fn next_value_seed<V: DeserializeSeed<'de>>(&mut self, seed: V) -> Result<V::Value, Error> {
        let path = &self.paths[self.next];
        self.next += 1;
        seed.deserialize(Tracer {
            prefix: path,
            keys: self.keys,
        })
    }
}

/// An array's elements, each traced at the array's key.
struct Elements<'a> {
    tracer: Tracer<'a>,
    left: usize,
}

impl<'de> de::SeqAccess<'de> for Elements<'_> {
    type Error = Error;

    fn next_element_seed<T: DeserializeSeed<'de>>(
        &mut self,
        seed: T,
    ) -> Result<Option<T::Value>, Error> {
        if self.left == 0 {
            return Ok(None);
        }
        self.left -= 1;
        seed.deserialize(self.tracer).map(Some)
    }
}

#[cfg(test)]
mod tests {
    /// The tracer walks the whole file's shape: nested tables, arrays of tables, and the
    /// structs of other modules (`[[machine]]`, `[[notify]]`).
    #[test]
    fn every_table_and_key_is_found() {
        let keys = super::all().unwrap();
        for key in [
            "spool.dir",
            "farm.on_shutdown",
            "history.keep_days",
            "printer.pause_heaters_off_s",
            "printer.simulate.seed",
            "machine.bed_mm",
            "folder.settings",
            "notify.name",
        ] {
            assert!(keys.iter().any(|k| k == key), "{key} in {keys:?}");
        }
        assert_eq!(
            super::tables().unwrap(),
            [
                "spool",
                "control",
                "farm",
                "machine",
                "printer",
                "folder",
                "http",
                "store",
                "history",
                "notify",
                "camera",
                "spoolman",
                "enhancement",
                "maintenance"
            ]
        );
    }
}
