#pragma once
// One parsing rule for every JSON document kdrt reads into a DOM (render requests, config files;
// ray batches use their own SAX reader with the same rules): syntax errors name the byte, a
// number outside the range of a double (1e400) names the member instead of escaping as an
// exception, and a member given twice in one object is refused (never "the last one wins").

#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/proto/result.h"

namespace kdrt::proto::detail {

/// Parses `text`; on failure the error is a sentence naming where and what.
template <class Json>
Result<Json, std::string> parse_json_strict(std::string_view text, bool ignore_comments = false) {
    std::vector<std::set<std::string>> seen;  // the keys of each open object
    std::vector<std::string> names;           // the current key of each open object
    std::string duplicate;
    const auto dotted = [&] {
        std::string out;
        for (const std::string& n : names) {
            if (n.empty()) continue;
            if (!out.empty()) out += '.';
            out += n;
        }
        return out;
    };
    typename Json::parser_callback_t callback = [&](int, typename Json::parse_event_t event,
                                                    Json& parsed) {
        using Event = typename Json::parse_event_t;
        if (event == Event::object_start) {
            seen.emplace_back();
            names.emplace_back();
        } else if (event == Event::object_end) {
            if (!seen.empty()) seen.pop_back();
            if (!names.empty()) names.pop_back();
        } else if (event == Event::key && !seen.empty()) {
            const std::string key = parsed.template get<std::string>();
            names.back() = key;
            if (!seen.back().insert(key).second && duplicate.empty()) duplicate = dotted();
        }
        return true;
    };
    try {
        Json doc = Json::parse(text, callback, /*allow_exceptions=*/true, ignore_comments);
        if (!duplicate.empty())
            return Err{"duplicate member \"" + duplicate + "\" (each member may appear once)"};
        return doc;
    } catch (const typename Json::parse_error& e) {
        std::string what = e.what();
        const size_t bracket = what.find("] ");
        if (bracket != std::string::npos) what.erase(0, bracket + 2);
        return Err{"invalid JSON at byte " + std::to_string(e.byte) + ": " + what};
    } catch (const typename Json::exception& e) {
        // out_of_range 406: a number too large for a double. The member being read is known.
        std::string what = e.what();
        const size_t bracket = what.find("] ");
        if (bracket != std::string::npos) what.erase(0, bracket + 2);
        const std::string where = dotted();
        return Err{(where.empty() ? std::string("a value") : "\"" + where + "\"") + ": " + what +
                   " (outside the range of a double)"};
    }
}

}  // namespace kdrt::proto::detail
