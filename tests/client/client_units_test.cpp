// In-process tests of the pieces without a server: server URLs, errors from responses, the
// CLI's argument and value parsers, its output formats and progress reporting.

#include <gtest/gtest.h>

#include <sstream>

#include "cli_args.h"
#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_progress.h"
#include "kdrt/client/error.h"
#include "kdrt/client/server_url.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"

namespace kdrt {
namespace {

TEST(ServerUrl, ParsesSchemesHostsPortsAndPrefixes) {
    struct Case {
        const char* text;
        const char* scheme;
        const char* host;
        int port;
        const char* base;
    };
    for (const Case& c : {Case{"http://127.0.0.1:8080", "http", "127.0.0.1", 8080, ""},
                          Case{"127.0.0.1:9", "http", "127.0.0.1", 9, ""},
                          Case{"localhost", "http", "localhost", 80, ""},
                          Case{"https://kdrt.example.org", "https", "kdrt.example.org", 443, ""},
                          Case{"HTTP://host:1/api/kdrt/", "http", "host", 1, "/api/kdrt"},
                          Case{"http://[::1]:8080/", "http", "::1", 8080, ""},
                          Case{"http://[::1]", "http", "::1", 80, ""}}) {
        SCOPED_TRACE(c.text);
        auto url = parse_server_url(c.text);
        ASSERT_TRUE(url) << url.error();
        EXPECT_EQ(url->scheme, c.scheme);
        EXPECT_EQ(url->host, c.host);
        EXPECT_EQ(url->port, c.port);
        EXPECT_EQ(url->base_path, c.base);
    }
    EXPECT_EQ(parse_server_url("http://[::1]:81/x")->to_string(), "http://[::1]:81/x");
    EXPECT_EQ(parse_server_url("h:7")->to_string(), "http://h:7");
}

TEST(ServerUrl, RefusesMalformedAddressesNamingTheProblem) {
    struct Case {
        const char* text;
        const char* phrase;
    };
    for (const Case& c :
         {Case{"ftp://host", "unknown scheme \"ftp\""}, Case{"http://", "no host"},
          Case{"http://:80", "no host"}, Case{"http://host:", "empty port"},
          Case{"http://host:0", "not a number in 1 .. 65535"},
          Case{"http://host:65536", "not a number in 1 .. 65535"},
          Case{"http://host:8x", "not a number in 1 .. 65535"},
          Case{"http://host?x=1", "no query or fragment"},
          Case{"http://user:pw@host", "user information"},
          Case{"http://ho st", "is not a host name"}, Case{"http://[::1", "unterminated ["},
          Case{"http://[zz]", "is not an IPv6 address"}, Case{"http://[::1]x", "expected :PORT"}}) {
        SCOPED_TRACE(c.text);
        auto url = parse_server_url(c.text);
        ASSERT_FALSE(url);
        EXPECT_NE(url.error().find(c.phrase), std::string::npos) << url.error();
        EXPECT_NE(url.error().find(c.text), std::string::npos) << url.error();
    }
}

TEST(ClientError, FromProblemJson) {
    proto::Problem p;
    p.kind = proto::ProblemKind::kMeshParseError;
    p.detail = "line 4: face index 9 out of range";
    p.line = 4;
    p.request_id = "0000000000000007";
    const Error e =
        error_from_response(422, "application/problem+json", proto::encode_problem(p), "ignored");
    EXPECT_EQ(e.kind, ErrorKind::kServer);
    EXPECT_EQ(e.status, 422);
    EXPECT_EQ(e.title, "Mesh parse error");
    EXPECT_EQ(e.type, "urn:kdrt:problem:mesh-parse-error");
    EXPECT_EQ(e.detail, p.detail);
    EXPECT_EQ(e.line, 4u);
    EXPECT_FALSE(e.byte_offset);
    EXPECT_EQ(e.request_id, "0000000000000007");
    EXPECT_EQ(e.to_string(), "422 Mesh parse error: line 4: face index 9 out of range");

    p.kind = proto::ProblemKind::kOverCapacity;
    p.retry_after = 3;
    p.limit = 64;
    p.code = "x";
    p.request_id.clear();
    const Error busy =
        error_from_response(503, "text/plain", proto::encode_problem(p), "00000000000000ff");
    EXPECT_EQ(busy.title, "Over capacity");  // decoded though mislabelled: it is a problem document
    EXPECT_EQ(busy.retry_after, 3u);
    EXPECT_EQ(busy.limit, 64u);
    EXPECT_EQ(busy.code, "x");
    EXPECT_EQ(busy.request_id, "00000000000000ff");
}

TEST(ClientError, FromOtherBodies) {
    const Error html = error_from_response(502, "text/html", "<h1>Bad\r\ngateway</h1>\n");
    EXPECT_EQ(html.title, "Bad Gateway");
    EXPECT_EQ(html.detail, "<h1>Bad  gateway</h1>");
    EXPECT_TRUE(html.type.empty());
    const Error long_body = error_from_response(500, "", std::string(1000, 'x'));
    EXPECT_EQ(long_body.detail, std::string(300, 'x') + "...");
    EXPECT_EQ(error_from_response(418, "", "").title, "Client Error");
    EXPECT_EQ(error_from_response(599, "", "").title, "Server Error");
    EXPECT_EQ(error_from_response(404, "application/problem+json", "{not json").title, "Not Found");
    EXPECT_EQ(error_from_response(404, "", "").to_string(), "404 Not Found");
    const Error local = make_client_error(ErrorKind::kInput, "cannot upload", "cannot open \"x\"");
    EXPECT_EQ(local.to_string(), "cannot upload: cannot open \"x\"");
    EXPECT_EQ(error_kind_name(ErrorKind::kConnection), "connection");
    EXPECT_EQ(error_kind_name(ErrorKind::kJobFailed), "job_failed");
}

TEST(CliExitCodes, FollowTheErrorKind) {
    const auto code = [](ErrorKind kind) {
        return cli::exit_code_for(make_client_error(kind, "t", "d"));
    };
    EXPECT_EQ(code(ErrorKind::kServer), cli::kExitRefused);
    EXPECT_EQ(code(ErrorKind::kProtocol), cli::kExitRefused);
    EXPECT_EQ(code(ErrorKind::kJobFailed), cli::kExitRefused);
    EXPECT_EQ(code(ErrorKind::kCancelled), cli::kExitRefused);
    EXPECT_EQ(code(ErrorKind::kInput), cli::kExitUsage);
    EXPECT_EQ(code(ErrorKind::kConnection), cli::kExitUnreachable);
}

TEST(CliCommands, TheTableDrivesDispatchAndTheMainHelp) {
    ASSERT_FALSE(cli::commands().empty());
    for (const cli::Command* c : cli::commands()) {
        SCOPED_TRACE(std::string(c->name));
        EXPECT_EQ(cli::find_command(c->name), c);
        // A family (kdrt scene) runs its subcommands, each named "<family> <subcommand>".
        ASSERT_NE(c->run == nullptr, c->subcommands.empty());
        EXPECT_EQ(c->synopsis.substr(0, c->name.size()), c->name);
        EXPECT_EQ(c->help.rfind("usage: kdrt " + std::string(c->name), 0), 0u);
        // One line of the main help per command: the synopsis, then the summary.
        const size_t line = cli::main_help().find("\n  " + std::string(c->synopsis) + " ");
        ASSERT_NE(line, std::string::npos);
        EXPECT_NE(cli::main_help().find(std::string(c->summary) + "\n", line), std::string::npos);
        for (const cli::OptionSpec& o : c->options)
            EXPECT_NE(c->help.find("--" + std::string(o.name)), std::string_view::npos) << o.name;
        for (const cli::Command* sub : c->subcommands) {
            SCOPED_TRACE(std::string(sub->name));
            ASSERT_NE(sub->run, nullptr);
            EXPECT_EQ(sub->name.rfind(std::string(c->name) + " ", 0), 0u);
            EXPECT_EQ(sub->help.rfind("usage: kdrt " + std::string(sub->name), 0), 0u);
            EXPECT_NE(c->help.find(std::string(sub->synopsis)), std::string_view::npos);
            for (const cli::OptionSpec& o : sub->options)
                EXPECT_NE(sub->help.find("--" + std::string(o.name)), std::string_view::npos)
                    << o.name;
        }
    }
    EXPECT_EQ(cli::find_command("help"), nullptr);  // handled by dispatch, not a table entry
    EXPECT_EQ(cli::find_command("frob"), nullptr);
}

TEST(CliArgs, SplitsOptionsFlagsAndPositionals) {
    const cli::OptionSpec specs[] = {{"output", true, 'o'}, {"json", false}, {"size", true}};
    const std::vector<std::string> args = {"a",          "-o", "x.png",  "--json",
                                           "--size=3x4", "--", "--json", "-5"};
    auto parsed = cli::parse_args(args, specs, "kdrt t");
    ASSERT_TRUE(parsed) << parsed.error();
    EXPECT_EQ(parsed->positional, (std::vector<std::string>{"a", "--json", "-5"}));
    EXPECT_EQ(parsed->value("output"), "x.png");
    EXPECT_EQ(parsed->value("size"), "3x4");
    EXPECT_TRUE(parsed->has("json"));
    EXPECT_FALSE(parsed->has("missing"));
    const std::vector<std::string> negative = {"-1,2,3", "--output", "-"};
    auto neg = cli::parse_args(negative, specs, "kdrt t");
    ASSERT_TRUE(neg) << neg.error();
    EXPECT_EQ(neg->positional, std::vector<std::string>{"-1,2,3"});
    EXPECT_EQ(neg->value("output"), "-");
}

TEST(CliArgs, ErrorsNameTheOptionAndTheCommand) {
    const cli::OptionSpec specs[] = {{"output", true, 'o'}, {"json", false}};
    const auto error = [&](std::vector<std::string> args) {
        auto parsed = cli::parse_args(args, specs, "kdrt t");
        return parsed ? std::string() : parsed.error();
    };
    EXPECT_EQ(error({"--nope"}), "unknown option \"--nope\" for kdrt t (see kdrt t --help)");
    EXPECT_EQ(error({"-x"}), "unknown option \"-x\" for kdrt t (see kdrt t --help)");
    EXPECT_EQ(error({"-o"}), "option -o needs a value (see kdrt t --help)");
    EXPECT_EQ(error({"--json=1"}), "option --json takes no value (see kdrt t --help)");
}

TEST(CliArgs, GlobalSettingsFromFlagsAndEnvironment) {
    const std::vector<cli::OptionSpec> specs(std::begin(cli::kGlobalOptions),
                                             std::end(cli::kGlobalOptions));
    const auto settings = [&](std::vector<std::string> args,
                              const std::map<std::string, std::string>& env) {
        return cli::global_settings(*cli::parse_args(args, specs, "kdrt t"), env);
    };
    EXPECT_EQ(settings({}, {})->server, "http://127.0.0.1:8080");
    EXPECT_EQ(settings({}, {{"KDRT_SERVER", "http://h:1"}})->server, "http://h:1");
    EXPECT_EQ(settings({"--server", "h:2"}, {{"KDRT_SERVER", "http://h:1"}})->server, "h:2");
    auto full = settings({"--token", "t", "--timeout", "2.5", "--retries", "0"}, {});
    ASSERT_TRUE(full) << full.error();
    EXPECT_EQ(full->token, "t");
    EXPECT_EQ(full->timeout_s, 2.5);
    EXPECT_EQ(full->retries, 0u);
    EXPECT_FALSE(settings({"--server", "ftp://x"}, {}));
    EXPECT_FALSE(settings({}, {{"KDRT_SERVER", "http://h:0"}}));
    EXPECT_EQ(settings({"--timeout", "0"}, {}).error(),
              "--timeout: \"0\" is not a positive number of seconds");
    EXPECT_EQ(settings({"--retries", "x"}, {}).error(), "--retries: \"x\" is not a whole number");
    EXPECT_EQ(settings({"--retries", "101"}, {}).error(), "--retries: \"101\" is not in 0 .. 100");
}

TEST(CliArgs, ValueParsers) {
    EXPECT_EQ(*cli::parse_size("1024x768"), (std::pair<uint32_t, uint32_t>{1024, 768}));
    EXPECT_EQ(*cli::parse_size("1X1"), (std::pair<uint32_t, uint32_t>{1, 1}));
    for (const char* bad : {"1024", "0x5", "5x0", "x5", "5x", "axb", "16385x1", "-1x5"}) {
        SCOPED_TRACE(bad);
        EXPECT_FALSE(cli::parse_size(bad));
    }
    EXPECT_EQ(*cli::parse_vec3("1,-2.5,+3e1"), (Vec3{1, -2.5f, 30}));
    for (const char* bad : {"1,2", "1,2,3,4", "1,,3", "a,b,c", "nan,0,0", "inf,0,0", "1e39,0,0"}) {
        SCOPED_TRACE(bad);
        EXPECT_FALSE(cli::parse_vec3(bad));
    }
    EXPECT_EQ(*cli::parse_region("0,8,16,32"), (PixelRegion{0, 8, 16, 32}));
    EXPECT_FALSE(cli::parse_region("0,0,0,5"));
    EXPECT_FALSE(cli::parse_region("0,0,5"));
    EXPECT_EQ(*cli::parse_uint("42", 1, 100), 42u);
    EXPECT_EQ(cli::parse_uint("", 0, 1).error(), "\"\" is not a whole number");
    EXPECT_EQ(cli::parse_uint("99999999999999999999", 0, 1).error(),
              "\"99999999999999999999\" is not in 0 .. 1");
    EXPECT_FALSE(cli::parse_uint("4.5", 0, 10));
    EXPECT_EQ(*cli::parse_number("-0.25"), -0.25);
    EXPECT_FALSE(cli::parse_number("1e999"));
    EXPECT_FALSE(cli::parse_number("2x"));
    EXPECT_EQ(cli::image_format_for_path("a/b.PNG"), "png");
    EXPECT_EQ(cli::image_format_for_path("x.jpeg"), "jpg");
    EXPECT_EQ(cli::image_format_for_path("x.jpg"), "jpg");
    EXPECT_EQ(cli::image_format_for_path("x.exr"), "exr");
    EXPECT_FALSE(cli::image_format_for_path("x.bmp"));
    EXPECT_FALSE(cli::image_format_for_path("png"));
}

TEST(CliOutput, JsonLinesCarryTheServerFields) {
    proto::MeshSummary m;
    m.id = std::string(64, 'a');
    m.triangles = 12;
    m.vertices = 8;
    m.bounds = Aabb{{0, 0, 0}, {1, 1, 1}};
    m.tree.build_ms = 1.25;
    m.in_memory = true;
    const std::string plain = cli::mesh_json_line(m);
    EXPECT_EQ(plain, proto::encode_mesh_summary(m));
    const std::string with_file = cli::mesh_json_line(m, "dir/a \"b\".obj");
    EXPECT_EQ(with_file.rfind("{\"file\":\"dir/a \\\"b\\\".obj\",\"id\":\"aaaa", 0), 0u)
        << with_file;
    EXPECT_EQ(cli::upload_line(m, "x.obj"), m.id + "  12 triangles  1.2 ms  x.obj");
    const std::string table = cli::mesh_table(std::vector<proto::MeshSummary>{m});
    EXPECT_EQ(table.rfind("ID ", 0), 0u);
    EXPECT_NE(table.find(m.id + "  " + "         12" + "          8" + "       1.2" + "  yes\n"),
              std::string::npos)
        << table;
    const std::string details = cli::mesh_details(m);
    EXPECT_NE(details.find("triangles   12\n"), std::string::npos);
    EXPECT_NE(details.find(
                  "bounds      [0.000000, 0.000000, 0.000000] .. [1.000000, 1.000000, 1.000000]\n"),
              std::string::npos)
        << details;
}

TEST(CliProgress, PlainLinesEveryTenPercent) {
    std::ostringstream err;
    cli::ProgressReporter p(err, /*tty=*/false, /*quiet=*/false, "render");
    p.update("queued", 0);
    p.update("queued", 0);
    for (double x : {0.0, 0.05, 0.12, 0.19, 0.5, 0.99, 1.0}) p.update("running", x);
    p.update("done", 1.0);
    p.finish("done in 1.00 s");
    EXPECT_EQ(err.str(),
              "render: queued\nrender: 0%\nrender: 10%\nrender: 50%\nrender: 90%\nrender: 100%\n"
              "render: done in 1.00 s\n");
}

TEST(CliProgress, BarOnATerminal) {
    EXPECT_EQ(cli::ProgressReporter::bar("running", 0.5, 10), "[#####-----]  50% running");
    EXPECT_EQ(cli::ProgressReporter::bar("done", 1.0, 4), "[####] 100% done");
    EXPECT_EQ(cli::ProgressReporter::bar("queued", -1, 2), "[--]   0% queued");
    std::ostringstream err;
    cli::ProgressReporter p(err, /*tty=*/true, false, "render");
    p.update("running", 0.25);
    p.update("running", 0.25);
    p.update("done", 1.0);
    p.finish("done in 0.10 s");
    const std::string text = err.str();
    EXPECT_EQ(std::count(text.begin(), text.end(), '\r'), 2);
    EXPECT_NE(text.find("\rrender: [#######"), std::string::npos) << text;
    EXPECT_NE(text.find("100% done"), std::string::npos);
    EXPECT_NE(text.find("\nrender: done in 0.10 s\n"), std::string::npos);
    std::ostringstream quiet_err;
    cli::ProgressReporter quiet(quiet_err, true, /*quiet=*/true, "render");
    quiet.update("running", 0.5);
    quiet.finish("done");
    EXPECT_TRUE(quiet_err.str().empty());
}

}  // namespace
}  // namespace kdrt
