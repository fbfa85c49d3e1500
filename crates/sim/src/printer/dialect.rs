//! What differs between the firmware flavours in what they say: `M115` and its `Cap:`
//! lines, and which G/M codes a stock build knows.
use super::state::Printer;
use crispen_marlin::firmware::Firmware;

/// A Marlin 2.0 build as commonly configured: no ADVANCED_OK.
const MARLIN20_CAPS: [&str; 5] = [
    "EEPROM:1",
    "AUTOREPORT_TEMP:1",
    "EMERGENCY_PARSER:1",
    "HOST_ACTION_COMMANDS:1",
    "BUSY_PROTOCOL:1",
];

const MARLIN21_CAPS: [&str; 27] = [
    "SERIAL_XON_XOFF:0",
    "BINARY_FILE_TRANSFER:0",
    "EEPROM:1",
    "VOLUMETRIC:1",
    "AUTOREPORT_POS:0",
    "AUTOREPORT_TEMP:1",
    "PROGRESS:0",
    "PRINT_JOB:1",
    "AUTOLEVEL:0",
    "Z_PROBE:0",
    "LEVELING_DATA:0",
    "BUILD_PERCENT:1",
    "SOFTWARE_POWER:0",
    "TOGGLE_LIGHTS:0",
    "CASE_LIGHT_BRIGHTNESS:0",
    "EMERGENCY_PARSER:1",
    "HOST_ACTION_COMMANDS:1",
    "PROMPT_SUPPORT:0",
    "SDCARD:0",
    "AUTOREPORT_SD_STATUS:0",
    "THERMAL_PROTECTION:1",
    "MOTION_MODES:0",
    "ARCS:1",
    "BABYSTEPPING:0",
    "CHAMBER_TEMPERATURE:0",
    "BUSY_PROTOCOL:1",
    "ADVANCED_OK:1",
];

impl Printer {
    pub(super) fn m115(&mut self) {
        let (version, caps): (&str, &[&str]) = match self.fw {
            Firmware::Ultimaker2 => {
                return self.say(
                    "FIRMWARE_NAME:Marlin Ultimaker2; Sprinter/grbl mashup for gen6 \
                     FIRMWARE_URL:https://github.com/Ultimaker/Ultimaker2Marlin \
                     PROTOCOL_VERSION:1.0 MACHINE_TYPE:Ultimaker EXTRUDER_COUNT:1",
                )
            }
            Firmware::Marlin20 => ("2.0.9.3", &MARLIN20_CAPS),
            Firmware::Marlin2 => ("2.1.2", &MARLIN21_CAPS),
        };
        self.say(&format!(
            "FIRMWARE_NAME:Marlin {version} (crispen sim) \
             SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin PROTOCOL_VERSION:1.0 \
             MACHINE_TYPE:crispen sim EXTRUDER_COUNT:1 UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff"
        ));
        for cap in caps {
            let name = cap.split(':').next().unwrap_or(cap);
            match name {
                "ADVANCED_OK" => {
                    let on = u8::from(self.advanced_ok);
                    self.say(&format!("Cap:ADVANCED_OK:{on}"))
                }
                "EMERGENCY_PARSER" => {
                    let on = u8::from(self.emergency_parser);
                    self.say(&format!("Cap:EMERGENCY_PARSER:{on}"))
                }
                _ => self.say(&format!("Cap:{cap}")),
            }
        }
    }
}

/// G/M codes a typical Marlin 2 build knows (enough for slicer output); others get
/// `echo:Unknown command`.
pub(super) fn known_marlin2(letter: char, code: f64) -> bool {
    let whole = code.trunc() as i64;
    match letter {
        'G' => matches!(
            whole,
            0..=5 | 10 | 11 | 12 | 17..=21 | 26..=30 | 33 | 34 | 38 | 42 | 53..=61 | 76 | 80 | 90..=92
        ),
        'M' => matches!(
            whole,
            0 | 1 | 3..=5 | 16..=34 | 42 | 48 | 73 | 75..=78 | 80..=92 | 100 | 104..=125
                | 140 | 141 | 145 | 149 | 150 | 155 | 163 | 164 | 190 | 191 | 200..=209
                | 211 | 217..=221 | 226 | 240 | 250 | 256 | 260..=261 | 280 | 281 | 290
                | 300 | 301 | 302..=306 | 350 | 351 | 355 | 360 | 380 | 381 | 400..=422
                | 425 | 428 | 430 | 486 | 500..=504 | 510..=512 | 524 | 540 | 569 | 575
                | 600 | 603 | 605 | 665 | 666 | 672 | 701 | 702 | 710 | 808 | 810..=813
                | 851 | 852 | 860..=869 | 871 | 876 | 900 | 906 | 907..=919 | 928 | 993..=999
        ),
        'T' => true,
        _ => false,
    }
}

impl Printer {
    /// `M503`: the settings report, line for line as each firmware writes it (Marlin
    /// 2.1.2.1: `MarlinSettings::report` in settings.cpp, every value with two decimals;
    /// Ultimaker2Marlin: `Config_PrintSettings` in ConfigurationStore.cpp, the maximum
    /// accelerations as whole numbers), from the planner's settings as they stand.
    pub(super) fn m503(&mut self) {
        use crispen_marlin::estimate::Junction;
        let l = &self.settings;
        let axes = |v: &[f64; 4], whole: bool| {
            let f = |x: f64| {
                if whole {
                    format!("{x:.0}")
                } else {
                    format!("{x:.2}")
                }
            };
            format!("X{} Y{} Z{} E{}", f(v[0]), f(v[1]), f(v[2]), f(v[3]))
        };
        let lines: Vec<String> = match self.fw {
            Firmware::Ultimaker2 => {
                let (xy, z, e) = match l.junction {
                    Junction::Classic { xy, z, e } => (xy, z, e),
                    Junction::Deviation { .. } => (0.0, 0.0, 0.0),
                };
                vec![
                    "echo:Steps per unit:".into(),
                    format!("echo:  M92 {}", axes(&l.steps_per_mm, false)),
                    "echo:Maximum feedrates (mm/s):".into(),
                    format!("echo:  M203 {}", axes(&l.max_feedrate, false)),
                    "echo:Maximum Acceleration (mm/s2):".into(),
                    format!("echo:  M201 {}", axes(&l.max_accel, true)),
                    "echo:Acceleration: S=acceleration, T=retract acceleration".into(),
                    format!("echo:  M204 S{:.2} T{:.2}", l.accel, l.retract_accel),
                    "echo:Advanced variables: S=Min feedrate (mm/s), T=Min travel feedrate (mm/s), \
                     B=minimum segment time (ms), X=maximum XY jerk (mm/s),  Z=maximum Z jerk \
                     (mm/s),  E=maximum E jerk (mm/s)"
                        .into(),
                    format!(
                        "echo:  M205 S{:.2} T{:.2} B{:.0} X{xy:.2} Z{z:.2} E{e:.2}",
                        l.min_feedrate, l.min_travel_feedrate, l.min_segment_time_us
                    ),
                    "echo:Home offset (mm):".into(),
                    "echo:  M206 X0.00 Y0.00 Z0.00".into(),
                    "echo:PID settings:".into(),
                    "echo:   M301 P10.00 I2.50 D100.00".into(),
                ]
            }
            Firmware::Marlin2 | Firmware::Marlin20 => {
                let jd = match l.junction {
                    Junction::Deviation { mm } => mm,
                    Junction::Classic { .. } => 0.0,
                };
                vec![
                    "echo:; Linear Units:".into(),
                    "echo:  G21 ; (mm)".into(),
                    "echo:; Temperature Units:".into(),
                    "echo:  M149 C ; Units in Celsius".into(),
                    "echo:; Filament settings (Disabled):".into(),
                    "echo:  M200 S0 D1.75".into(),
                    "echo:; Steps per unit:".into(),
                    format!("echo:  M92 {}", axes(&l.steps_per_mm, false)),
                    "echo:; Max feedrates (units/s):".into(),
                    format!("echo:  M203 {}", axes(&l.max_feedrate, false)),
                    "echo:; Max Acceleration (units/s2):".into(),
                    format!("echo:  M201 {}", axes(&l.max_accel, false)),
                    "echo:; Acceleration (units/s2) (P<print-accel> R<retract-accel> T<travel-accel>):"
                        .into(),
                    format!(
                        "echo:  M204 P{:.2} R{:.2} T{:.2}",
                        l.accel,
                        l.retract_accel,
                        l.travel_accel.unwrap_or(l.accel)
                    ),
                    "echo:; Advanced (B<min_segment_time_us> S<min_feedrate> \
                     T<min_travel_feedrate> J<junc_dev>):"
                        .into(),
                    format!(
                        "echo:  M205 B{:.2} S{:.2} T{:.2} J{jd:.2}",
                        l.min_segment_time_us, l.min_feedrate, l.min_travel_feedrate
                    ),
                    "echo:; Home offset:".into(),
                    "echo:  M206 X0.00 Y0.00 Z0.00".into(),
                    "echo:; Hotend PID:".into(),
                    "echo:  M301 P22.20 I1.08 D114.00".into(),
                ]
            }
        };
        for line in lines {
            self.say(&line);
        }
    }
}
