// Context: what every subcommand run shares (connection, messages, mesh id prefixes).

#include "cli_context.h"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <vector>

#include "kdrt/proto/file_io.h"
#include "kdrt/proto/image_module.h"
#include "kdrt/proto/mesh_id.h"

namespace kdrt::cli {

int exit_code_for(const Error& error) noexcept {
    switch (error.kind) {
        case ErrorKind::kConnection:
            return kExitUnreachable;
        case ErrorKind::kInput:
            return kExitUsage;
        case ErrorKind::kServer:
        case ErrorKind::kProtocol:
        case ErrorKind::kJobFailed:
        case ErrorKind::kCancelled:
            break;
    }
    return kExitRefused;
}

ClientOptions Context::client_options() const {
    ClientOptions options;
    options.token = settings.token;
    if (settings.timeout_s)
        options.io_timeout =
            std::chrono::milliseconds(static_cast<int64_t>(std::ceil(*settings.timeout_s * 1000)));
    if (settings.retries) options.max_retries = *settings.retries;
    return options;
}

Client& Context::connect(const ClientOptions& options) {
    client.emplace(settings.server, options);
    return *client;
}

int Context::usage_error(std::string_view message) const {
    console.err << "kdrt " << command << ": " << message << "\n"
                << "run 'kdrt " << command << " --help' for usage\n";
    return kExitUsage;
}

int Context::fail(const Error& error, std::string_view subject) const {
    console.err << "kdrt " << command << ": "
                << (subject.empty() ? "" : std::string(subject) + ": ") << error.to_string()
                << "\n";
    if (error.kind == ErrorKind::kConnection)
        console.err
            << "is kdrt-server running there? Set the address with --server URL or KDRT_SERVER.\n";
    if (error.kind == ErrorKind::kServer && error.status == 401)
        console.err << "set the server's bearer token with --token TOKEN or KDRT_TOKEN.\n";
    return exit_code_for(error);
}

proto::Result<std::string, int> Context::resolve_mesh_id(std::string_view arg) {
    if (proto::is_mesh_id(arg)) return std::string(arg);
    std::string prefix(arg);
    std::transform(prefix.begin(), prefix.end(), prefix.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    const bool hex = prefix.size() >= 4 && prefix.size() < proto::kMeshIdLength &&
                     prefix.find_first_not_of("0123456789abcdef") == std::string::npos;
    if (!hex) return std::string(arg);  // the server explains what is wrong with it
    auto list = client->meshes();
    if (!list) return proto::Err{fail(list.error())};
    std::vector<std::string> matches;
    for (const MeshInfo& m : *list)
        if (m.id.rfind(prefix, 0) == 0) matches.push_back(m.id);
    if (matches.empty()) {
        console.err << "kdrt " << command << ": no stored mesh has an id starting with " << prefix
                    << "\n";
        return proto::Err{static_cast<int>(kExitRefused)};
    }
    if (matches.size() > 1)
        return proto::Err{usage_error("mesh id prefix " + prefix +
                                      " is ambiguous: " + std::to_string(matches.size()) +
                                      " stored meshes start with it; give more digits")};
    return matches.front();
}

std::optional<int> Context::need_image_module() const {
    auto module = proto::image_module();
    if (module) return std::nullopt;
    console.err << "kdrt " << command << ": " << module.error() << "\n";
    return kExitRefused;
}

std::string Context::format_path(const std::string& output) const {
    if (auto format = args.value("format")) return "x." + *format;
    return output;
}

std::optional<int> Context::write_output(const std::string& output,
                                         std::span<const std::byte> bytes,
                                         std::string_view what) const {
    if (is_stdout(output)) {
        console.out.write(reinterpret_cast<const char*>(bytes.data()),
                          static_cast<std::streamsize>(bytes.size()));
        console.out.flush();
        if (console.out) return std::nullopt;
        return fail(make_client_error(ErrorKind::kInput, "cannot write " + std::string(what),
                                      "standard output is closed or full"));
    }
    if (auto written = proto::write_file_bytes(output, bytes); !written)
        return fail(make_client_error(ErrorKind::kInput, "cannot write " + std::string(what),
                                      written.error()));
    return std::nullopt;
}

void Context::report(std::string_view output, std::string_view human,
                     std::string_view json_line) const {
    if (json()) {
        (is_stdout(output) ? console.err : console.out) << json_line << "\n";
    } else if (!quiet()) {
        console.err << human << "\n";
    }
}

bool positional_count_ok(Context& ctx, size_t min, size_t max, std::string_view what, int& code) {
    const size_t n = ctx.args.positional.size();
    if (n < min) {
        code = ctx.usage_error("missing " + std::string(what));
        return false;
    }
    if (n > max) {
        code = ctx.usage_error("unexpected argument \"" + ctx.args.positional[max] + "\"");
        return false;
    }
    return true;
}

}  // namespace kdrt::cli
