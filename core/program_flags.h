// Command-line parsing shared by every Kinetri binary.
//
// Abseil's `--help` lists only flags defined in a file named after the
// program, so for binaries like `kinetri-server` (flags in server/main.cc) it
// printed "No flags matched." and exited 1. ParseProgramFlags makes `--help`
// and `--helpshort` list the program's own flags (every flag defined outside
// Abseil itself) and exit 0. This is a separate library from kinetri::core:
// it depends only on Abseil's flags.
#ifndef KINETRI_CORE_PROGRAM_FLAGS_H_
#define KINETRI_CORE_PROGRAM_FLAGS_H_

#include <vector>

#include "absl/strings/string_view.h"

namespace kinetri {

// Sets `usage` as the program's usage message, makes `--help` list the
// program's own flags, parses argv and returns the positional arguments
// (argv[0] first), as absl::ParseCommandLine does.
std::vector<char*> ParseProgramFlags(int argc, char** argv,
                                     absl::string_view usage);

// True for a flag defined in one of Kinetri's files (not in Abseil).
bool IsProgramFlagFile(absl::string_view filename);

}  // namespace kinetri

#endif  // KINETRI_CORE_PROGRAM_FLAGS_H_
