#include "core/program_flags.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "absl/flags/commandlineflag.h"
#include "absl/flags/parse.h"
#include "absl/flags/reflection.h"
#include "absl/flags/usage.h"
#include "absl/flags/usage_config.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace kinetri {
namespace {

// `first` followed by `text` wrapped at 78 columns, continuation lines
// indented by `indent` spaces.
std::string Wrap(absl::string_view first, absl::string_view text, int indent) {
  std::string out, line(first);
  const std::string pad(indent, ' ');
  size_t pos = 0;
  while (pos < text.size()) {
    size_t end = text.find(' ', pos);
    if (end == absl::string_view::npos) end = text.size();
    const absl::string_view word = text.substr(pos, end - pos);
    if (!line.empty() && line.size() + 1 + word.size() > 78) {
      absl::StrAppend(&out, line, "\n");
      line = pad;
    }
    if (!word.empty()) {
      if (!line.empty() && line != pad) line += ' ';
      absl::StrAppend(&line, word);
    }
    pos = end + 1;
  }
  if (!line.empty()) absl::StrAppend(&out, line, "\n");
  return out;
}

// Prints the usage message and the program's own flags (those whose name,
// help or default contain `filter`, if given) to stdout.
void PrintHelp(absl::string_view filter) {
  std::string out = absl::StrCat(absl::ProgramUsageMessage(), "\n\n");
  std::vector<absl::CommandLineFlag*> flags;
  for (const auto& [name, flag] : absl::GetAllFlags()) {
    if (!IsProgramFlagFile(flag->Filename())) continue;
    if (!filter.empty() && !absl::StrContains(name, filter) &&
        !absl::StrContains(flag->Help(), filter)) {
      continue;
    }
    flags.push_back(flag);
  }
  std::sort(flags.begin(), flags.end(),
            [](const absl::CommandLineFlag* a, const absl::CommandLineFlag* b) {
              return a->Name() < b->Name();
            });
  absl::StrAppend(&out, "Flags:\n");
  for (const absl::CommandLineFlag* f : flags) {
    std::string def = f->DefaultValue();
    if (f->IsOfType<std::string>()) def = absl::StrCat("\"", def, "\"");
    absl::StrAppend(&out,
                    Wrap(absl::StrCat("  --", f->Name()),
                         absl::StrCat(f->Help(), " (default: ", def, ")"), 6));
  }
  absl::StrAppend(&out, "\n",
                  Wrap("  --help",
                       "this text (also --helpshort); --help=TEXT: only flags "
                       "mentioning TEXT; --helpfull: Abseil's flags too",
                       6));
  std::fputs(out.c_str(), stdout);
}

}  // namespace

bool IsProgramFlagFile(absl::string_view filename) {
  return !absl::StrContains(filename, "absl/");
}

std::vector<char*> ParseProgramFlags(int argc, char** argv,
                                     absl::string_view usage) {
  absl::FlagsUsageConfig config;
  config.contains_help_flags = IsProgramFlagFile;
  config.contains_helpshort_flags = IsProgramFlagFile;
  absl::SetFlagsUsageConfig(config);
  absl::SetProgramUsageMessage(usage);
  // Abseil answers --help with exit status 1; a help request is not an error.
  for (int i = 1; i < argc; ++i) {
    absl::string_view arg = argv[i];
    if (arg == "--") break;
    if (!absl::ConsumePrefix(&arg, "--")) absl::ConsumePrefix(&arg, "-");
    if (arg == "help" || arg == "helpshort" || arg == "h") {
      PrintHelp("");
      std::exit(0);
    }
    if (absl::ConsumePrefix(&arg, "help=")) {
      PrintHelp(arg);
      std::exit(0);
    }
  }
  return absl::ParseCommandLine(argc, argv);
}

}  // namespace kinetri
